"""Benchmarks and their synthetic inputs: outside the installed packages, run from the repository root.

``python -m benchmarks [--only NAME ...] [--quick] [--json FILE]`` (``make bench``) runs every benchmark
(``suite``); each module also runs alone (``python -m benchmarks.bench_solver`` ...). ``synthetic`` makes
paper-size CVVC problems and models for the solver benchmark and the tests. The bridge's own benchmarks are
still ``simulator_bridge/bench.py`` and ``simulator_bridge/bench_bridge.py``.
"""
