"""The quarantine: the one place that drives OpenDSS (``dss_context`` alone imports opendssdirect), the feeder engine,
its readout and tables, the local controls and their check against OpenDSS's own loop.
"""
