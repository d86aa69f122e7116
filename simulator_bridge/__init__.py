"""The physics and the simulated field devices: the only package that imports OpenDSS (``engine``)."""
