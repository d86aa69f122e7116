"""The simulated field devices and their contracts (no Zenoh): PV plants, regulators, banks, meters, SunSpec
inverters.
"""
