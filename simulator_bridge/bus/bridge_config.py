"""What a bridge run needs: :class:`BridgeConfig` (built by ``cvvc bridge``, launchers and tests; read by the
bridge's loop and its runtime).
"""

from __future__ import annotations

from typing import Literal

import msgspec

from schemas.settings import BridgeSection

__all__ = ["BridgeConfig"]

_REALISM = BridgeSection()  # the realism defaults are a case file's [bridge] section's (``schemas.settings``)


class BridgeConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Everything a bridge run needs (built by the ``cvvc bridge`` handler, or by tests and launchers).

    Attributes
    ----------
    device_map_path : the feeder's device map TOML.
    feeder_id : id in the key space (default: the map's ``feeder.name``).
    start : first simulated instant, ``YYYY-MM-DD`` or ``YYYY-MM-DDTHH:MM`` local standard time (UTC-5),
        within the profile year. steps : number of steps to simulate.
    clock : ``lockstep`` or ``realtime``. timeout_s : lockstep wall-clock wait per control step [s].
    speed : real-time speed factor (simulated seconds per wall second).
    wait_agent_s : before the first step, wait up to this long for an agent liveliness token [s].
    year_seed : profile seed. pv_local : PV local default (``unity`` or ``volt_var``).
    truth_every : publish a TruthFrame every N steps (0: never).
    noise_pmu_pct, noise_scada_pct : measurement noise per class [%]; drop_prob : frame drop probability;
    latency_s : fixed frame latency [s of wall time]; noise_seed : seed of noise and drops.
    drop_burst_min : with ``drop_prob``, each device loses its frames in outages of this many minutes, ``drop_prob``
        being the share of frames lost (0: each frame independently).
    clock_skew_s : the field devices' clocks are this far off the bridge's (and so the agent's) [s]: frames are
        stamped ``t + clock_skew_s``.
    cache_dir : where profiles are cached as ``.npz`` (None: no cache).
    publisher : who builds, encodes and puts a step's frames, metrics update, truth and metrics frames:
        ``inline`` the stepping thread; ``process`` a publisher process with its own Zenoh session, while the
        stepping thread solves the next step (not with ``latency_s``; the bus must have connect or listen
        endpoints and no config file); ``auto`` (default) the process on feeders of 200 nodes or more when it
        can, inline otherwise. The messages are the same.
    oracle : serve the case-A oracle (``sim/oracle``: every node's true voltage and perturbation sensitivities).
        Off by default: it exists only when case A asks for it (``cvvc run --case A`` sets it), and then answers
        at most ``ORACLE_REPLIES_PER_STEP`` queries per simulated step; the rest are refused and counted
        (``oracle_rate``): each reply costs the stepping thread K + R + 2 power flows.
    pv_sunspec : plant id -> ``tcp/127.0.0.1:PORT``: these plants are behind simulated SunSpec inverters served
        there, and a ``cvvc adapter sunspec --clock head`` per plant publishes their frames and acks and takes
        their commands (``simulator_bridge.bus.sunspec_fleet``); the bridge waits, up to ``timeout_s``, for each
        adapter's frame of a step before the next one.
    field_dnp3 : device id -> ``tcp/127.0.0.1:PORT``: these regulators and capacitor banks are behind simulated DNP3
        outstations served there, and a ``cvvc adapter dnp3 --clock head`` per device publishes their frames and
        acks and operates their commands (``simulator_bridge.bus.dnp3_fleet``); waited for as ``pv_sunspec``.
    own_commands_only : subscribe to this feeder's commands only (``cvvc/<id>/cmd/**``), not to every feeder's
        (``cvvc/*/cmd/**``, which answers a command sent to a feeder without a bridge: ``wrong_feeder``). For
        many feeders on one bus (``cvvc fleet``): each bridge otherwise receives every feeder's commands, and one
        that drains its queue late refuses, on their ack keys, commands of feeders whose bridge has finished.
    """

    device_map_path: str
    feeder_id: str | None = None
    start: str = "2023-07-01"
    steps: int = 1440
    clock: Literal["lockstep", "realtime"] = "lockstep"
    timeout_s: float = 5.0
    speed: float = 1.0
    wait_agent_s: float = 0.0
    year_seed: int = 1
    pv_local: Literal["unity", "volt_var"] = "unity"
    truth_every: int = _REALISM.truth_every
    noise_pmu_pct: float = _REALISM.noise_pmu_pct
    noise_scada_pct: float = _REALISM.noise_scada_pct
    drop_prob: float = _REALISM.drop_prob
    latency_s: float = 0.0
    noise_seed: int = 0
    cache_dir: str | None = None  # year-profile cache folder; None: no cache (the CLI passes its --cache's)
    publisher: Literal["auto", "inline", "process"] = "auto"
    oracle: bool = False
    drop_burst_min: float = _REALISM.drop_burst_min
    clock_skew_s: float = _REALISM.clock_skew_s
    pv_sunspec: dict[str, str] = {}  # plant id -> tcp/127.0.0.1:PORT: the plant behind a simulated SunSpec inverter
    own_commands_only: bool = False
    field_dnp3: dict[str, str] = {}  # regulator or bank id -> tcp/127.0.0.1:PORT: the device behind a DNP3 outstation
