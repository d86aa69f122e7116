"""Closed-loop runs side by side: ``cvvc run`` on IEEE 13 with a model, once per variant, started together (the
machine has two cores; each waits on its own processes), each killed by its pid if it outlives its deadline.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run_side_by_side(work: Path, model: Path, variants: dict[str, list[str]], *, days: float, start: str,
                     timeout_s: float = 300.0) -> dict[str, tuple[Path, dict]]:
    """Run ``cvvc run`` of case D on IEEE 13 for ``days`` from ``start``, once per variant (its extra flags), in
    ``work``; returns, by variant, its output folder and its JSON summary. The profile year (seed 2) is made once
    into ``work/cache`` first rather than by every run at the same time.
    """
    from schemas.cache import profiles_dir
    from tests.yearcache import cache_year_profiles

    feeder = REPO / "feeders" / "ieee13.toml"
    cache_year_profiles(feeder, profiles_dir(str(work / "cache")), seed=2)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    procs = {}
    for name, extra in variants.items():
        args = [sys.executable, "-m", "cvvc", "run", "--feeder", str(feeder), "--model", str(model),
                "--days", str(days), "--start", start, "--out", str(work / name), "--cache", str(work / "cache"),
                "--no-baseline", "--json", *extra]
        procs[name] = subprocess.Popen(args, cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                       text=True)
    out = {}
    try:
        for name, proc in procs.items():
            stdout, stderr = proc.communicate(timeout=timeout_s)
            assert proc.returncode == 0, f"{name}: {stderr[-3000:]}"
            out[name] = (work / name, json.loads(stdout))
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    return out
