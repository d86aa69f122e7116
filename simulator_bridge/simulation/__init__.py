"""Simulated time: year profiles, the QSTS stepping, the paper's metrics, live accuracy, the oracle."""
