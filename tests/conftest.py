"""Shared fixtures (free loopback ports, a router-mode Zenoh session, paths to the shared test feeders, a trained
IEEE 13 model, the profile cache, a clock the test sets and simulated DNP3 outstations on it) and the test tiers.

Tiers (docs/testing.md): a test that opens a Zenoh session is marked ``bus``, one that starts processes (``cvvc``
programs, a Dask cluster, a publisher process) ``process``, one that trains a model on a real feeder or runs a
closed loop or an evaluation ``slow``. ``make check`` runs the tests with none of the three; ``make test`` runs
every test. A test is marked by the fixtures it uses (``_MARKS_BY_FIXTURE``, its whole fixture closure counts), by
its module's ``pytestmark`` or on itself; each tier has its own timeout (``TIMEOUT_S``), the longest of the
test's tiers.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_FEEDERS = (REPO.parent / "shared" / "feeders").resolve()

# the fixtures that put a test in a tier (a test using one, directly or through another fixture, is marked)
_MARKS_BY_FIXTURE: dict[str, tuple[str, ...]] = {
    "router_endpoint": ("bus",),          # a router-mode Zenoh session
    "secure_router": ("bus",),            # tests/schemas/test_security.py: a router with the access policy
    "fleet_router": ("bus",),             # tests/cvvc/test_fleet.py: a secure router of two feeders
    "dask_scheduler": ("process",),       # tests/cvvc/conftest.py: a LocalCluster of two worker processes
    "user_cluster": ("process",),         # tests/cvvc/test_campaign.py: a scheduler and workers as programs
    "campaign_out": ("process", "slow"),  # tests/cvvc/test_campaign.py: a campaign of evaluations on them
    "model13": ("process", "slow"),       # tests/reliability/conftest.py: ``cvvc train`` as a program
    "procs": ("process",),                # tests/reliability/conftest.py: ``cvvc`` programs on the bus
    "cvvc_program": ("process",),         # tests/adapters/conftest.py: ``cvvc adapter`` programs
    "ieee13_model": ("slow",),            # IEEE 13 trained on real power flows
    "trained_123": ("slow",),             # tests/training/conftest.py: IEEE 123 trained on real power flows
    "models": ("slow",),                  # tests/training/test_extended.py: IEEE 13 with banks, trained twice
    "calendar_model": ("slow",),          # tests/training/test_extended.py
    "banks_only": ("slow",),              # tests/training/test_bank_sensitivities.py
    "one_hour_run": ("process", "slow"),  # tests/cvvc/test_run.py: one ``cvvc run`` of an hour
    "both_runs": ("process", "slow"),     # tests/cvvc/test_run_sunspec.py
    "dnp3_runs": ("process", "slow"),     # tests/cvvc/test_run_dnp3.py
    "ami_run": ("process", "slow"),       # tests/cvvc/test_ami_run.py
    "caps_run": ("process", "slow"),      # tests/cvvc/test_run_caps.py
    "small_evaluation": ("process", "slow"),  # tests/cvvc/test_evaluate.py
    "tiny_evaluation": ("process", "slow"),   # tests/cvvc/test_report.py
}

# per-test timeout of each tier [s] (setup and teardown included: the first test to use a session fixture pays it)
TIMEOUT_S = {"fast": 60, "bus": 120, "process": 180, "slow": 600}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark each test by the fixtures it uses, then give it its tiers' timeout unless it names its own."""
    for item in items:
        for fixture in getattr(item, "fixturenames", ()):
            for name in _MARKS_BY_FIXTURE.get(fixture, ()):
                if item.get_closest_marker(name) is None:
                    item.add_marker(name)
        if item.get_closest_marker("timeout") is None:
            tiers = [t for t in ("bus", "process", "slow") if item.get_closest_marker(t) is not None] or ["fast"]
            item.add_marker(pytest.mark.timeout(max(TIMEOUT_S[t] for t in tiers)))


@pytest.fixture(scope="session", autouse=True)
def _user_cache_in_tmp(tmp_path_factory) -> Iterator[Path]:
    """No test writes into the user's cache: the default cache root (schemas.cache) points into a tmp folder."""
    import os

    folder = tmp_path_factory.mktemp("xdg-cache")
    before = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(folder)
    yield folder
    if before is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = before


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """A router-mode Zenoh session listening on a free tcp/127.0.0.1 port; yields its endpoint."""
    from schemas.bus import BusConfig, free_port, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session(BusConfig(mode="router", listen=(endpoint,))):
        yield endpoint


@pytest.fixture
def repo_root() -> Path:
    return REPO


@pytest.fixture
def shared_feeders() -> Path:
    return SHARED_FEEDERS


@pytest.fixture(scope="session")
def ieee13_model(tmp_path_factory) -> Path:
    """A model trained on IEEE 13 (real OpenDSS power flows, ~4 s), once per test session."""
    from regression.model import write_model
    from schemas.settings import TrainingOptions
    from training.train import train

    out = tmp_path_factory.mktemp("ieee13-model") / "model.json"
    result = train(REPO / "feeders" / "ieee13.toml", TrainingOptions(blocks=(3, 3)),
                   cache_dir=tmp_path_factory.getbasetemp() / "profiles", progress=False)
    write_model(result.model, out)
    return out


@pytest.fixture(scope="session")
def profile_cache(tmp_path_factory) -> Path:
    """One profile cache for the whole session (profiles of a feeder and seed take seconds to make).

    Files are named by feeder, fingerprint and seed, so every test shares it; its parent is a cache root
    (``cache=`` of a run or evaluation finds it as ``<root>/profiles``).
    """
    folder = tmp_path_factory.getbasetemp() / "profiles"
    folder.mkdir(exist_ok=True)
    return folder


@pytest.fixture(scope="session")
def sharing_profiles(profile_cache: Path):
    """Makes ``folder`` a fresh cache root (a run's ``--cache``) whose year profiles are the session's
    (``profile_cache``): a run still makes its own CA, keys and models there, but loads the profiles another test
    made instead of making them again (seconds per feeder and seed). Returns the folder.
    """

    def make(folder: Path) -> Path:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "profiles").symlink_to(profile_cache, target_is_directory=True)
        return folder

    return make


class SetClock:
    """A clock [ns since the epoch] that only the test moves (``t_ns``): simulated devices' timers and adapters."""

    def __init__(self, t_ns: int) -> None:
        self.t_ns = t_ns

    def __call__(self) -> int:
        return self.t_ns


@pytest.fixture
def clock() -> SetClock:
    """A :class:`SetClock` at 1000 s."""
    return SetClock(1_000 * 10**9)


@pytest.fixture
def regulator_outstation(clock):
    """Start a simulated regulator control ``reg1`` (DNP3, on ``clock``, a free port) with the measurements given
    as keywords (``set_measurements``) and, if given, its ``setpoint_range_v120``; it stops at the end of the test.
    """
    from contextlib import ExitStack

    from schemas.bus import free_port
    from simulator_bridge.field.dnp3_sim import SimulatedRegulatorControl

    with ExitStack() as stack:
        def start(setpoint_range_v120=None, **measurements):
            limits = {} if setpoint_range_v120 is None else {"setpoint_range_v120": setpoint_range_v120}
            sim = stack.enter_context(SimulatedRegulatorControl(
                regulator_id="reg1", tap_max=16, default_setpoint_v120=120.0, default_band_v120=2.0,
                port=free_port(), clock_ns=clock, **limits))
            sim.set_measurements(**measurements)
            return sim

        yield start


@pytest.fixture
def bank_outstation(clock):
    """Start a simulated capacitor bank controller ``cap1`` (DNP3, on ``clock``, a free port), open, measuring
    ``v_v`` [V] without a control value; it stops at the end of the test.
    """
    from contextlib import ExitStack

    from schemas.bus import free_port
    from simulator_bridge.field.dnp3_sim import SimulatedCapBankController

    with ExitStack() as stack:
        def start(v_v: float):
            sim = stack.enter_context(SimulatedCapBankController(capacitor_id="cap1", port=free_port(),
                                                                 clock_ns=clock))
            sim.set_measurements(closed=False, v_v=v_v, control_value=None)
            return sim

        yield start
