"""Fixtures of the adapter tests: a simulated SunSpec inverter on a free loopback port and its clock, and ``cvvc``
programs run as processes."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from schemas.bus import free_port
from simulator_bridge.field.sunspec_sim import SimulatedSunSpecInverter

REPO = Path(__file__).resolve().parents[2]
RATING_KVA = 1000.0
P_PHASE_KW = 200.0  # 600 kW: headroom sqrt(1000² − 600²) = 800 kvar


class ShiftedClock:
    """Wall time [ns since the epoch] plus an offset the test may move forward (the inverter's revert timer)."""

    def __init__(self) -> None:
        self.offset_ns = 0

    def __call__(self) -> int:
        return time.time_ns() + self.offset_ns


@pytest.fixture
def inverter_clock() -> ShiftedClock:
    return ShiftedClock()


def _inverter(clock: ShiftedClock, single_master: bool) -> SimulatedSunSpecInverter:
    inv = SimulatedSunSpecInverter(plant_id="pv1", s_rated_kva=RATING_KVA, v_nominal_v=7200.0, port=free_port(),
                                   clock_ns=clock, single_master=single_master)
    inv.set_measurements(p_kw=[P_PHASE_KW] * 3, v_v=[7250.0, 7260.0, 7270.0])
    return inv


@pytest.fixture
def inverter(inverter_clock) -> Iterator[SimulatedSunSpecInverter]:
    """An inverter that takes writes from its registered Modbus master only (the first connection)."""
    with _inverter(inverter_clock, single_master=True) as inv:
        yield inv


@pytest.fixture
def open_inverter(inverter_clock) -> Iterator[SimulatedSunSpecInverter]:
    """An inverter that takes writes from any Modbus connection (no master setting): a second master can write."""
    with _inverter(inverter_clock, single_master=False) as inv:
        yield inv


@pytest.fixture
def cvvc_program() -> Iterator[Callable[..., subprocess.Popen]]:
    """Start ``python -m cvvc ARGS...`` (this checkout first on the path, text pipes); those still running at the
    end of the test are killed.
    """
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    started: list[subprocess.Popen] = []

    def start(*args: str) -> subprocess.Popen:
        proc = subprocess.Popen([sys.executable, "-m", "cvvc", *args], env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=20)
