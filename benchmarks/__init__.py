"""Benchmarks and their synthetic inputs: outside the installed packages, run from the repository root.

``python -m benchmarks [--only NAME ...] [--quick] [--json FILE]`` (``make bench``) runs every benchmark
(``suite``); each module also runs alone (``python -m benchmarks.bench_solver`` ...). ``synthetic`` makes
paper-size CVVC problems and models for the solver benchmark and the tests. ``bench_qsts`` (the QSTS against
bare OpenDSS) and ``bench_bridge`` (lockstep bridge against the bare QSTS) measure the simulator.
"""
