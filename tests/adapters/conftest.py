"""Fixtures of the adapter tests: a simulated SunSpec inverter on a free loopback port, and its clock."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from schemas.bus import free_port
from simulator_bridge.field.sunspec_sim import SimulatedSunSpecInverter

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
