"""The one settings tree of a run (``cvvc run case.toml``): frozen structs, every default written once, here.

A case file is this tree in TOML (``cvvc init case.toml`` writes it with every setting, its default and its
description). Its sections::

    case = "D"            # the paper's case (A-D) or a baseline (none, local)
    cache = ...           # the cache root (models, profiles, certificates)
    [feeder]              # FeederSection: the device map, the model and its training year
    [window]              # WindowSection: the simulated days and their profile year
    [agent]               # AgentOptions: the agent's decision settings (the part of AgentSettings a case may set)
    [bridge]              # BridgeSection: the bridge's clock and realism (noise, lost frames, delays, skew)
    [output]              # OutputSection: the run's folder, recording and baseline
    [security]            # SecuritySection: mTLS and the access policy, the certificate authority

``TrainingOptions`` (with its ``FeatureOptions``) is what ``cvvc train`` and ``training.train.train`` train with;
a run trains its model with the defaults and the feeder's feature options (``training.extended``).

``AgentSettings`` (what the agent process decides with, recorded with every session) is ``AgentOptions`` plus what
the case and the feeder fix (feeder id, mode, correction, full visibility, AMI meters); ``CvvcController``'s keyword
defaults, ``cvvc run``'s flags, ``RunConfig`` and the bridge's realism defaults all read their defaults from here.
Every field's ``Meta(description=...)`` is the line ``cvvc init`` writes above it: a new setting is one field here.
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec
from msgspec import Meta

from schemas.devicemap import MeterSpec

__all__ = ["ANSI_RANGE_A_PU", "CASES", "DEFAULT_COMBINED_PCT", "DEFAULT_Q_STEPS_PCT", "PAPER_AGENT", "SECTIONS",
           "AgentOptions", "AgentSettings", "BridgeSection", "Case", "FeatureOptions", "FeatureSet", "FeederSection",
           "FieldProtocol", "OutputSection", "PvProtocol", "RunCase", "SecuritySection", "TrainingOptions",
           "WindowSection"]

Case = Literal["A", "B", "C", "D", "none", "local"]
CASES: tuple[Case, ...] = ("A", "B", "C", "D", "none", "local")
PvProtocol = Literal["bus", "sunspec"]
FieldProtocol = Literal["bus", "dnp3"]
FeatureSet = Literal["paper", "extended", "extended_readings"]
DEFAULT_Q_STEPS_PCT: tuple[float, ...] = tuple(float(p) for p in range(-100, 101, 20))
DEFAULT_COMBINED_PCT: tuple[float, ...] = (-100.0, -50.0, 50.0, 100.0)

class AgentOptions(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The agent's decision settings (docs/agent.md); the case sets the mode and the correction."""

    bandwidth_v120: Annotated[float, Meta(gt=0, description=(
        "regulator band sent with eq. (8) set points, cases C/D [V on the 120 V base]"))] = 4.0
    valid_intervals: Annotated[float, Meta(gt=0, description=(
        "commands expire this many control periods after their step"))] = 2.0
    late_window_s: Annotated[float, Meta(ge=0, description=(
        "live only: how long an incomplete step waits for late frames [s]"))] = 2.0
    stale_after_s: Annotated[float, Meta(gt=0, description="live only: no frame for this long -> 'stale' [s]")] = 10.0
    oracle_timeout_s: Annotated[float, Meta(gt=0, description=(
        "case A: how long to wait for the bridge's oracle [s]"))] = 30.0
    pv_margin_window_s: Annotated[float, Meta(ge=0, description=(
        "beyond the paper: PV variability margin window, 0 = off (the paper's method) [s]"))] = 1800.0
    pv_margin_cap_pu: Annotated[float, Meta(ge=0, le=0.05, description=(
        "the PV variability margin's largest value on either side [pu]"))] = 0.01
    drift_margin: Annotated[bool, Meta(description=(
        "estimated states: each node's limits also tightened by how far its estimate moved against the last "
        "decision's prediction over the last two control periods, where both moved it the same way (capped like the "
        "PV margin)"))] = False
    # (first 3 days of each season: epri-k1 winter's 1-minute minimum met, goals missed on IEEE 13, 123 and epri-k1
    # 8 -> 7, IEEE 8500 the same 8 with more tap changes; docs/method.md "Drift margin and the deadband's hold")
    setpoint_hold: Annotated[bool, Meta(description=(
        "beyond the paper, cases C/D: re-send the last set point when no tap change is decided"))] = False
    control_banks: Annotated[bool, Meta(description=(
        "beyond the paper, cases B-D: decide and command the capacitor banks"))] = False
    reading_window_s: Annotated[float, Meta(ge=0, description=(
        "regulator readings averaged over this at the present tap [s]; 0: the last reading"))] = 300.0
    # (600 s let the nominal rural winter week violate: NVV 8)
    last_good_s: Annotated[float, Meta(ge=0, description=(
        "a head/PV/regulator frame lost at a control step: its latest within this stands in [s]"))] = 900.0
    # (240 s held 82 and 278 steps and gave NVV 597 and 1,158 with 10-minute outages in the rural winter week)
    reading_fit_s: Annotated[float, Meta(ge=0, description=(
        "> 0: regulator readings of this long regressed on the head's P and Q [s]; 0: off"))] = 0.0
    clock_tolerance_s: Annotated[float, Meta(ge=0, description=(
        "a frame stamped this close to a control step is that step's (clock skew) [s]"))] = 5.0
    correction_window_s: Annotated[float, Meta(ge=0, description=(
        "eq. (6)'s corrections: exponential mean over about this [s]; 0: off"))] = 3000.0
    # (rural winter week with 1 % SCADA noise: NVV 10 -> 0, NTC 196 -> 66; agent.state.CorrectionFilter)
    filtered_setpoints: Annotated[bool, Meta(description=(
        "beyond the paper: eq. (8) from the estimate plus the filtered reading residual (with the correction "
        "filter); line-drop compensation as read where the readings are quiet"))] = True
    # (rural winter week with 1 % SCADA noise: NTC 66 -> 25, summer 134 -> 73; CvvcController)
    sensitivity_error: Annotated[float, Meta(ge=0, le=1, description=(
        "soft form: relative error of the estimated Q sensitivities; 0: the paper's eq. (17) [-]"))] = 0.3
    # (epri-ckt24, first winter day: plants pulling against each other, Q cost 2,130 -> 57 at NVV 435 -> 441)
    bounds_in_margin: Annotated[bool, Meta(description=(
        "the estimate bounds tighten a limit only past the optimization/judged gap"))] = True
    soft_precision: Annotated[bool, Meta(description=(
        "soft form (eq. 17): a node whose bounds are more than 3x the median node's weighs (3 x median / its "
        "bound)^2; off: every node alike (the paper's)"))] = True
    # (epri-ckt24 without meters, first winter day: node-minutes outside the optimization limits 779,204 -> 130,081,
    # no control 227,005; docs/method.md "The soft form's node weights")
    bounds_cover_filter: Annotated[bool, Meta(description=(
        "the estimate bounds cover eq. (6) as computed and as filtered"))] = True
    # (agent.state.filter_gap_bounds_pu; epri-m1 case D, 1 July: 37 % of node-decisions outside the bounds without)
    tap_reversal_lockout_s: Annotated[float, Meta(ge=0, description=(
        "a regulator's move is not reversed within this unless needed [s]; 0: off"))] = 900.0
    tap_deadband_pu: Annotated[float, Meta(ge=0, le=0.02, description=(
        "estimated states: no tap moves for a violation of the tightened limits up to this [pu]; 0: off"))] = 0.004
    # (IEEE 8500, first three days of each season at 52c31b0: NTC 1.15-1.46x case A's but spring 1.75x, one
    # trajectory; docs/method.md "Tap deadband", docs/results.md)
    tap_deadband_hold_s: Annotated[float, Meta(ge=0, description=(
        "the tap deadband holds the taps for a violation at most this long in a row, then the move is taken; "
        "0: as long as the violation stays within it [s]"))] = 0.0
    # (300 s with the drift margin: IEEE 123 winter's 1-minute minimum 0.970 -> 0.973 pu, but goals missed on the four
    # larger feeders 23 -> 26; docs/method.md "Drift margin and the deadband's hold")
    tap_break_even: Annotated[bool, Meta(description=(
        "estimated states: Q that stands in for a tap move is paid until it has cost the move, then the tap "
        "moves (rent or buy)"))] = True
    setpoint_recentre: Annotated[bool, Meta(description=(
        "cases C/D: a regulator told to step by eq. (8) gets its band centred on its next step's reading"))] = True
    setpoint_safety: Annotated[bool, Meta(description=(
        "cases C/D: a held regulator's band narrowed so that its own control steps before the estimate of a node "
        "it moves would leave ANSI Range A"))] = True
    measured_tap_step: Annotated[bool, Meta(description=(
        "cases C/D: eq. (8) with each regulator's tap step as its compared reading measured it at its moves"))] = True
    predict_banks: Annotated[bool, Meta(description=(
        "banks on their local control: the decision keeps them from switching because of it"))] = True
    stale_plants: Annotated[bool, Meta(description=(
        "a plant behind a stale frame: P projected, Q our command, not raised, margin for its P"))] = True
    # (rural winter week, 5 % lost in 10-minute outages: NVV 3 -> 0, NTC 72 -> 25; 20 % outages: NTC 98 -> 70)


ANSI_RANGE_A_PU = (0.95, 1.05)
"""ANSI C84.1 service voltage Range A [pu of nominal]: every minute of a run is judged against it, and a held
regulator's band (``AgentOptions.setpoint_safety``) lets its own control step before a node leaves it."""

#: The paper's method: every option beyond the paper off (tests of the equations as the paper writes them).
PAPER_AGENT = AgentOptions(pv_margin_window_s=0.0, correction_window_s=0.0, filtered_setpoints=False,
                           sensitivity_error=0.0, bounds_in_margin=False, bounds_cover_filter=False,
                           tap_reversal_lockout_s=0.0, tap_deadband_pu=0.0, tap_break_even=False,
                           predict_banks=False,
                           stale_plants=False, soft_precision=False, setpoint_recentre=False,
                           measured_tap_step=False, setpoint_safety=False)


class AgentSettings(AgentOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Everything that shapes the agent's decisions (recorded with a session for the offline re-run): the options
    and what the case (mode, correction, full visibility) and the feeder (id, AMI meters) fix.
    """

    feeder_id: str = "rural-s1"
    agent_id: str = "agent"
    mode: Literal["taps", "setpoints"] = "setpoints"
    correction: bool = True
    full_visibility: bool = False
    # the device map's AMI meters ([[meter]]): the only meters whose readings count, each for its node and at its
    # interval in the map (agent.ami); none: every reading is refused
    meters: tuple[MeterSpec, ...] = ()


class FeederSection(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The feeder and the model."""

    map: Annotated[str | None, Meta(description=(
        "device map TOML or folder; not set: the embedded rural feeder"))] = None
    model: Annotated[str | None, Meta(description="model file; not set: trained once and cached")] = None
    train_seed: Annotated[int, Meta(description="profile year the model is trained on")] = 1


class WindowSection(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The simulated days (their steps are the device map's step_s, 1 minute)."""

    start: Annotated[str, Meta(description=(
        "first simulated instant, YYYY-MM-DD[THH:MM], local standard time (UTC-5)"))] = "2023-01-16"
    days: Annotated[float, Meta(gt=0, le=366, description="simulated days (1/24: one hour)")] = 1.0
    year_seed: Annotated[int, Meta(description="profile year of the run (2: out of sample, not the training year)")] = 2


class BridgeSection(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The simulator bridge's clock and realism."""

    realtime: Annotated[bool, Meta(description="step on the wall clock instead of lockstep")] = False
    speed: Annotated[float, Meta(gt=0, description="realtime: simulated seconds per wall second")] = 60.0
    lockstep_timeout_s: Annotated[float, Meta(gt=0, description=(
        "lockstep: how long the bridge waits for a decision before going on under local control [s]"))] = 10.0
    noise_pmu_pct: Annotated[float, Meta(ge=0, description="PMU-class noise on the feeder-head meter [%]")] = 0.0
    noise_scada_pct: Annotated[float, Meta(ge=0, description=(
        "SCADA-class noise on PV, regulator and capacitor readings [%]"))] = 0.0
    drop_prob: Annotated[float, Meta(ge=0, le=1, description=(
        "the bridge drops each measurement frame with this probability"))] = 0.0
    drop_burst_min: Annotated[float, Meta(ge=0, description=(
        "> 0: frames lost in per-device outages of this long, drop_prob the share lost [min]"))] = 0.0
    meas_delay_s: Annotated[float, Meta(ge=0, description=(
        "realtime only: frames reach the agent this late [simulated s]"))] = 0.0
    clock_skew_s: Annotated[float, Meta(description=(
        "the field devices' clocks are this far off the bridge's and the agent's [s]"))] = 0.0
    truth_every: Annotated[int, Meta(ge=0, description=(
        "a truth frame every this many steps (0: never); the recording keeps it for the metrics"))] = 1
    pv_protocol: Annotated[PvProtocol, Meta(description=(
        "how the PV plants reach the bus: bus (the bridge's frames) or sunspec (docs/sunspec.md)"))] = "bus"
    field_protocol: Annotated[FieldProtocol, Meta(description=(
        "how the regulators and capacitor banks reach the bus: bus (the bridge's frames) or dnp3 (each behind a "
        "simulated DNP3 outstation and a cvvc adapter dnp3; cases C, D, none and local; docs/dnp3.md)"))] = "bus"


class OutputSection(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The run's folder, its recording and its baseline."""

    out: Annotated[str | None, Meta(description="output folder; not set: runs/<feeder>-<case>-<time>")] = None
    record: Annotated[bool, Meta(description="record the session to MCAP (session.mcap)")] = True
    baseline: Annotated[bool, Meta(description="simulate the no-control baseline of the same days")] = True
    recorder_restarts_max: Annotated[int, Meta(ge=0, description=(
        "a recorder that dies is restarted at most this many times per run"))] = 3


class SecuritySection(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The bus's security (docs/security.md)."""

    secure: Annotated[bool, Meta(description=(
        "mTLS and the deny-by-default access policy (false: `--insecure`, warned and recorded)"))] = True
    ca_dir: Annotated[str | None, Meta(description=(
        "the certificate authority; not set: <cache>/ca, created on the first run"))] = None


class RunCase(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A case file: everything ``cvvc run`` runs (docs/case-file.md)."""

    case: Annotated[Case, Meta(description=(
        "paper case A-D, or a baseline: none (no central control), local (+ IEEE 1547 volt-var)"))] = "D"
    cache: Annotated[str | None, Meta(description=(
        "cache root (models, profiles, certificates); not set: the default cache"))] = None
    feeder: FeederSection = msgspec.field(default_factory=FeederSection)
    window: WindowSection = msgspec.field(default_factory=WindowSection)
    agent: AgentOptions = msgspec.field(default_factory=AgentOptions)
    bridge: BridgeSection = msgspec.field(default_factory=BridgeSection)
    output: OutputSection = msgspec.field(default_factory=OutputSection)
    security: SecuritySection = msgspec.field(default_factory=SecuritySection)


#: The sections of ``RunCase`` in the order a case file lists them.
SECTIONS: tuple[str, ...] = ("feeder", "window", "agent", "bridge", "output", "security")


class FeatureOptions(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The feature set of a model and its companions (docs/method.md "Extended features"; ``training.extended``
    names the paper's and the extended choice and picks one per feeder).
    """

    feature_set: Annotated[FeatureSet, Meta(description=(
        "paper: eq. (5) on head and plant P, Q; extended: plus the banks' state term, features mapped back to the "
        "training taps and banks; extended_readings: plus the field devices' voltage readings as regressors"))] = (
        "paper")
    calendar: Annotated[bool, Meta(description=(
        "extended sets only: time of day and day of year among the features"))] = False
    critical_margin_pu: Annotated[float, Meta(ge=0, description=(
        "> 0: the nodes within this of each flow's extremes covered by the critical nodes; 0: the paper's "
        "extremes only [pu]"))] = 0.0
    calendar_cover_per_cell: Annotated[int, Meta(ge=0, description=(
        "beyond the guided scenarios, this many minutes of every (month, local hour) cell, one base flow each"))] = 0
    calendar_seasonal: Annotated[int, Meta(ge=0, le=2, description=(
        "with calendar: the first 1 or 2 daily harmonics times the yearly one; 0: none"))] = 0
    calendar_weekly: Annotated[bool, Meta(description="with calendar: the weekend and its daily shape")] = False


class TrainingOptions(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What a model is trained with (paper II.A-II.D; ``training.train.train``); the model records them."""

    year_seed: Annotated[int, Meta(description="seed of the training year's profiles")] = 1
    selection: Annotated[Literal["guided", "random"], Meta(description=(
        "guided (paper II.A) or random (6 random minutes per block, the paper's Fig. 8a)"))] = "guided"
    blocks: Annotated[tuple[int, int], Meta(description="bins on the (load, PV) axes")] = (5, 5)
    q_steps_pct: Annotated[tuple[float, ...], Meta(description=(
        "PV Q steps (Algorithm 1 line 9) [% of kVA]"))] = DEFAULT_Q_STEPS_PCT
    combined_pct: Annotated[tuple[float, ...], Meta(description=(
        "extra flows with all plants at this share of their headroom at once; empty: none [%]"))] = (
        DEFAULT_COMBINED_PCT)
    tolerance: Annotated[float, Meta(gt=0, description=(
        "OpenDSS solve tolerance of the training flows (finite differences need 1e-8)"))] = 1e-8
    rcond: Annotated[float, Meta(gt=0, description="truncation of the eq. (5) least squares")] = 1e-6
    calibration_minutes: Annotated[int, Meta(ge=0, description=(
        "held-out minutes of the training year the estimate bounds are calibrated on; 0: no bounds (the "
        "paper's)"))] = 1440
    bound_alpha: Annotated[float, Meta(gt=0, lt=1, description=(
        "miscoverage of the calibrated two-sided bounds (0.01: the true voltage within them in 99 %)"))] = 0.01
    features: FeatureOptions = msgspec.field(default_factory=FeatureOptions)
