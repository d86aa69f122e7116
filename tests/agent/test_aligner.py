"""The frame aligner: grouping by timestamp, the hold/missing rule, and every rejection reason."""

from __future__ import annotations

import msgspec
import pytest

from agent.aligner import FrameAligner
from agent.errors import AgentInputError
from schemas import keys
from schemas import messages as m
from schemas.examples import examples

PERIOD_NS = 300_000_000_000
MINUTE = 60_000_000_000
T0 = 1_672_549_200_000_000_000  # a control step (multiple of 5 min)
EX = examples()


def head(t_ns, seq, **kw):
    return keys.meas_head("rural"), msgspec.structs.replace(EX[m.HeadFrame], t_ns=t_ns, seq=seq, **kw)


def pv(t_ns, seq, plant="pv1", **kw):
    return keys.meas_pv("rural", plant), msgspec.structs.replace(
        EX[m.PvFrame], t_ns=t_ns, seq=seq, plant_id=plant, source=plant, **kw)


def vr(t_ns, seq, reg="vr1a", **kw):
    return keys.meas_vr("rural", reg), msgspec.structs.replace(
        EX[m.RegFrame], t_ns=t_ns, seq=seq, regulator_id=reg, source=reg, **kw)


@pytest.fixture
def aligner():
    return FrameAligner(feeder_id="rural", pv_ids=("pv1",), regulator_ids=("vr1a",), control_period_ns=PERIOD_NS)


def test_complete_group_released_at_once(aligner):
    assert aligner.add(*head(T0, 1)) == []
    assert aligner.add(*pv(T0, 1)) == []
    out = aligner.add(*vr(T0, 1))
    assert len(out) == 1 and out[0].complete and out[0].t_ns == T0
    assert out[0].head.seq == 1 and set(out[0].pv) == {"pv1"} and set(out[0].vr) == {"vr1a"}
    assert not aligner.pending


def test_non_control_steps_are_not_released_as_decisions(aligner):
    t = T0 + 60_000_000_000
    for k, f in (head(t, 1), pv(t, 1), vr(t, 1)):
        assert aligner.add(k, f) == []
    assert not aligner.pending


def test_incomplete_group_closed_by_newer_frame_names_missing(aligner):
    aligner.add(*head(T0, 1))
    aligner.add(*vr(T0, 1))
    out = aligner.add(*head(T0 + 60_000_000_000, 2))
    assert len(out) == 1 and out[0].missing == ("pv1",)


def test_close_pending_releases_with_missing(aligner):
    aligner.add(*pv(T0, 1))
    aligner.add(*vr(T0, 1))
    (out,) = aligner.close_pending()
    assert out.head is None and out.missing == ("head",)


@pytest.mark.parametrize(
    ("frames", "kind"),
    [
        ([head(T0, 1, feeder_id="other")], "wrong_feeder"),
        ([("cvvc/other/meas/head", head(T0, 1)[1])], "wrong_feeder"),
        ([pv(T0, 1, plant="pv9")], "unknown_device"),
        ([head(T0, 5), head(T0 + 60_000_000_000, 5)], "duplicate"),
        ([head(T0, 5), head(T0 + 60_000_000_000, 4)], "out_of_order"),
        ([head(T0, 1, quality=["invalid"])], "implausible"),
        ([head(T0, 1, p_kw=99999.0)], "implausible"),
        ([pv(T0, 1, p_kw=5000.0)], "implausible"),
        ([vr(T0, 1, v_compared_120=60.0)], "implausible"),
    ],
)
def test_rejections_are_counted_by_reason(aligner, frames, kind):
    # the feeder's clock is set by two sources a step before (seq 0: every frame below has a higher one)
    aligner.add(*pv(T0 - MINUTE, 0))
    aligner.add(*vr(T0 - MINUTE, 0))
    for k, f in frames:
        aligner.add(k, f)
    assert aligner.rejected[kind] == 1
    assert sum(aligner.rejected.values()) == 1


def test_stale_frame_after_release_is_rejected(aligner):
    aligner.add(*head(T0, 1))
    aligner.add(*pv(T0, 1))
    aligner.add(*vr(T0, 1))
    aligner.add(*pv(T0, 2))  # a late duplicate of a released step: stale
    assert aligner.rejected["stale"] == 1


def test_good_frame_after_bad_is_handled(aligner):
    aligner.add(*head(T0, 1, feeder_id="other"))
    aligner.add(*head(T0, 2))
    aligner.add(*pv(T0, 1))
    (out,) = aligner.add(*vr(T0, 1))
    assert out.complete and out.head.seq == 2


# ------------------------------------------------------------------ no single frame moves the clock or locks out
def test_one_frame_from_the_future_does_not_blind_the_aligner(aligner):
    """A schema-valid head frame stamped 2100 made every real frame 'stale' for the rest of the run."""
    for k, f in (head(T0, 1), pv(T0, 1), vr(T0, 1)):
        aligner.add(k, f)
    forged_t = 4_102_444_800_000_000_000  # 2100-01-01
    assert aligner.add(*head(forged_t, 2)) == []
    assert aligner.close_pending() == []  # the runtime's late-frame window passes
    released = []
    for i in range(1, 11):  # ten real minutes go on as if nothing happened
        t = T0 + i * MINUTE
        for k, f in (head(t, 2 + i), pv(t, 1 + i), vr(t, 1 + i)):
            released += aligner.add(k, f)
    assert [a.t_ns for a in released] == [T0 + 5 * MINUTE, T0 + 10 * MINUTE]
    assert all(a.complete for a in released)
    assert aligner.rejected["stale"] == 0


def test_a_lone_frame_never_starts_the_clock(aligner):
    """Before any frame is accepted, a forged first frame waits for a second source and is pushed out later."""
    forged_t = 4_102_444_800_000_000_000
    aligner.add(*head(forged_t, 1))
    released = []
    for i in range(0, 6):
        t = T0 + i * MINUTE
        for k, f in (head(t, 2 + i), pv(t, 1 + i), vr(t, 1 + i)):
            released += aligner.add(k, f)
    assert [a.t_ns for a in released] == [T0, T0 + 5 * MINUTE]
    # a flood of lone forgeries from one source never confirms a jump; the bounded hold counts what it pushes out
    for i in range(20):
        released += aligner.add(*head(forged_t + i * 10**15, 100 + i))
    assert aligner.rejected["time_jump"] == 21 - 4 * 3  # 21 held in all, 12 kept
    assert not any(a.t_ns >= forged_t for a in released)


def test_a_burst_of_lost_frames_passes_at_once(aligner):
    """Ten minutes with no frame at all (a lost burst): the next step's devices agree, so it is taken at once."""
    for k, f in (head(T0, 1), pv(T0, 1), vr(T0, 1)):
        aligner.add(k, f)
    t = T0 + 10 * MINUTE
    assert aligner.add(*head(t, 2)) == []  # held: more than a period ahead, one source so far
    assert aligner.add(*pv(t, 2)) == []  # confirmed: head and pv taken
    (out,) = aligner.add(*vr(t, 2))
    assert out.t_ns == t and out.complete and sum(aligner.rejected.values()) == 0


def test_a_forged_huge_seq_is_refused_while_the_device_reports(aligner):
    """A head frame with seq 2**63-1 made the agent hold for the rest of the run; then it locked the
    head out for a control period. Now it is refused: the head's own sequence goes on."""
    for k, f in (head(T0, 1), pv(T0, 1), vr(T0, 1)):
        aligner.add(k, f)
    assert aligner.add(*head(T0 + MINUTE, 2**63 - 1)) == []
    released = []
    for i in range(2, 12):
        t = T0 + i * MINUTE
        for k, f in (head(t, i), pv(t, i), vr(t, i)):
            released += aligner.add(k, f)
    assert aligner.rejected == {"seq_jump": 1} and aligner.seq_resets == aligner.seq_jumps == 0
    assert [(a.t_ns, a.head is not None) for a in released] == [(T0 + 5 * MINUTE, True), (T0 + 10 * MINUTE, True)]


@pytest.mark.parametrize(("forged", "after_minute"), [
    ([(1, 10**6)], 0),  # a jump, before the minutes between arrive
    ([(1, 0)], 0),  # a 'restarted counter', a period past the head's last frame
    ([(1, 10**6), (2, 10**6 + 5)], 5),  # a jump, and its follower for the next step, both late
], ids=["jump", "reset", "late-jump-and-its-follower"])
def test_forged_frames_on_a_reporting_devices_key_never_take_a_step(forged, after_minute):
    """Near-future head frames stamped 3 s after the next control steps, put on the head's key (a forger that sees
    the head's frames). Before, a late forgery with a high seq was held and the forger's next one, going on from
    it, confirmed the 'jump' (the head's real frames then refused as out of order); one with a seq below the
    head's was taken as a restarted counter, its time being a period past the head's last frame."""
    snapping = FrameAligner(feeder_id="rural", pv_ids=("pv1",), regulator_ids=("vr1a",),
                            control_period_ns=PERIOD_NS, clock_tolerance_ns=5 * 10**9)
    released = []
    for i in range(0, 11):
        t = T0 + i * MINUTE
        for k, f in (head(t, 1 + i), pv(t, 1 + i), vr(t, 1 + i)):
            released += snapping.add(k, f)
        if i == after_minute:
            for steps, seq in forged:
                assert snapping.add(*head(T0 + steps * PERIOD_NS + 3 * 10**9, seq)) == []
    assert [(a.t_ns, a.head.seq, a.complete) for a in released] == [
        (T0, 1, True), (T0 + PERIOD_NS, 6, True), (T0 + 2 * PERIOD_NS, 11, True)]
    assert sum(snapping.rejected.values()) == len(forged) and snapping.accepted == 33
    assert snapping.seq_jumps == snapping.seq_resets == 0


def test_a_near_future_frame_with_a_high_seq_never_replaces_the_real_one(aligner):
    """A head frame stamped 3 s after the step (snapped onto it by the clock tolerance) with a high seq, sent before
    the step's real frames: the real head frame is the one decided on, and the forgery is counted."""
    snapping = FrameAligner(feeder_id="rural", pv_ids=("pv1",), regulator_ids=("vr1a",),
                            control_period_ns=PERIOD_NS, clock_tolerance_ns=5 * 10**9)
    for k, f in (head(T0, 1), pv(T0, 1), vr(T0, 1)):
        snapping.add(k, f)
    t = T0 + PERIOD_NS
    assert snapping.add(*head(t + 3 * 10**9, 10**6)) == []
    out = []
    for k, f in (head(t, 2), pv(t, 2), vr(t, 2)):
        out += snapping.add(k, f)
    assert len(out) == 1 and out[0].head.seq == 2 and out[0].complete
    assert snapping.rejected == {"seq_jump": 1}


def test_a_second_frame_of_a_device_for_the_same_time_is_a_duplicate_the_first_stays(aligner):
    aligner.add(*head(T0, 1))
    aligner.add(*head(T0, 2))
    aligner.add(*pv(T0, 1))
    (out,) = aligner.add(*vr(T0, 1))
    assert out.head.seq == 1 and aligner.rejected == {"duplicate": 1}


def test_a_device_whose_seq_really_jumps_is_taken_after_a_control_period(aligner):
    """The head's counter restarts from a saved value: its frames are refused until the others have reported a
    control period past its last frame of the old sequence, then its new sequence stands (one control step is
    decided without its frame)."""
    for k, f in (head(T0, 1), pv(T0, 1), vr(T0, 1)):
        aligner.add(k, f)
    released = []
    for i in range(1, 11):
        t = T0 + i * MINUTE
        for k, f in (head(t, 5000 + i), pv(t, 1 + i), vr(t, 1 + i)):
            released += aligner.add(k, f)
    assert aligner.rejected == {"seq_jump": 5} and aligner.seq_jumps == 1
    assert [(a.t_ns, a.missing) for a in released] == [(T0 + PERIOD_NS, ("head",)), (T0 + 2 * PERIOD_NS, ())]


def test_when_every_counter_restarts_the_new_sequences_are_taken_after_a_control_period(aligner):
    """A restarted bridge counts every device from 1 again two minutes after its last frames: each device's frames
    are refused until a control period has passed since the old sequences' last frames, then all are taken."""
    for i in range(0, 3):
        t = T0 + i * MINUTE
        for k, f in (head(t, 100 + i), pv(t, 100 + i), vr(t, 100 + i)):
            aligner.add(k, f)
    released = []
    for i in range(4, 16):
        t = T0 + i * MINUTE
        for k, f in (head(t, i), pv(t, i), vr(t, i)):
            released += aligner.add(k, f)
    assert aligner.seq_resets == 3 and aligner.rejected["out_of_order"] == 3 + 3 + 3 + 1
    assert [(a.t_ns, a.complete) for a in released] == [(T0 + 2 * PERIOD_NS, True), (T0 + 3 * PERIOD_NS, True)]


def test_capacitor_bank_frames_are_ignored_not_fatal(aligner):
    """A map with banks publishes CapFrames under meas/**: the agent does not use them yet and must not crash."""
    cap = msgspec.structs.replace(EX[m.CapFrame], t_ns=T0, seq=1)
    assert aligner.add(keys.meas_cap("rural", cap.capacitor_id), cap) == []
    assert aligner.ignored == 1 and sum(aligner.rejected.values()) == 0
    for k, f in (head(T0, 1), pv(T0, 1)):
        aligner.add(k, f)
    (out,) = aligner.add(*vr(T0, 1))
    assert out.complete


# ------------------------------------------------------------------ scan-end markers
def step_end(t_ns, *, head=True, pvs=(), vrs=(), feeder="rural", key_feeder="rural"):
    return keys.meas_step(key_feeder), m.StepEnd(t_ns=t_ns, seq=1, source="bridge", feeder_id=feeder, head=head,
                                                 pv=list(pvs), vr=list(vrs))


def test_a_step_end_releases_a_group_with_a_lost_frame_at_once(aligner):
    """The PV frame was lost: the marker says only the head and the regulator sent, so no late window is waited."""
    aligner.add(*head(T0, 1))
    aligner.add(*vr(T0, 1))
    assert aligner.pending
    out = aligner.add(*step_end(T0, vrs=["vr1a"]))
    assert [a.t_ns for a in out] == [T0] and out[0].missing == ("pv1",)
    assert not aligner.pending and aligner.released_by_step_end == 1 and aligner.step_ends == 1


def test_a_step_end_before_its_frames_releases_when_the_sent_ones_arrive(aligner):
    assert aligner.add(*head(T0, 1)) == []
    assert aligner.add(*step_end(T0, vrs=["vr1a"])) == []  # the regulator's frame is still on its way
    out = aligner.add(*vr(T0, 1))
    assert [a.t_ns for a in out] == [T0] and out[0].missing == ("pv1",)


def test_a_step_end_of_a_complete_or_decided_step_changes_nothing(aligner):
    for k, f in (head(T0, 1), pv(T0, 1), vr(T0, 1)):
        aligner.add(k, f)
    assert aligner.add(*step_end(T0, pvs=["pv1"], vrs=["vr1a"])) == []
    assert aligner.step_ends == 0 and aligner.released_by_step_end == 0


def test_a_forged_step_end_neither_moves_the_clock_nor_releases_a_group_without_frames(aligner):
    aligner.add(*head(T0, 1))
    aligner.add(*vr(T0, 1))
    far = T0 + 1000 * PERIOD_NS
    assert aligner.add(*step_end(far, head=False)) == []  # nothing arrived for that time: nothing to decide
    assert aligner.add(*step_end(T0 + PERIOD_NS, head=False)) == []
    assert aligner.pending  # the real step still waits for its frame
    out = aligner.add(*pv(T0, 1))
    assert [a.t_ns for a in out] == [T0] and out[0].complete
    assert aligner.add(*step_end(T0, feeder="other")) == [] and aligner.rejected["wrong_feeder"] == 1
    assert aligner.add(*step_end(T0, key_feeder="other")) == [] and aligner.rejected["wrong_feeder"] == 2


def test_step_end_markers_ahead_of_their_frames_are_bounded(aligner):
    from agent.aligner import _EXPECT_MAX

    aligner.add(*head(T0, 1))
    for i in range(1, 3 * _EXPECT_MAX):
        aligner.add(*step_end(T0 + i * MINUTE, head=False))
    assert len(aligner._expected) == _EXPECT_MAX


def test_a_control_step_carries_its_regulators_readings_of_the_period_and_the_snapshot_averages_them(aligner):
    """The regulator readings of the snapshot are the mean of the control
    period's frames at the present tap (a noisy single reading made the set points hunt)."""
    from agent.snapshot import snapshot_from
    from benchmarks.synthetic import synthetic_model

    base = EX[m.RegFrame]
    readings = [121.0, 119.0, 122.0, 118.0, 120.5, 119.5]  # minutes -5 .. 0 before the control step T0 + PERIOD
    taps = [2, 3, 3, 3, 3, 3]  # a tap change after the first: that reading is not averaged in
    out = []
    t1 = T0 + PERIOD_NS
    for i, (v, tap) in enumerate(zip(readings, taps, strict=True)):
        t = t1 - (len(readings) - 1 - i) * MINUTE
        ph = [msgspec.structs.replace(base.phases[0], v_120=v)]
        for k, f in (head(t, i + 1), pv(t, i + 1),
                     vr(t, i + 1, phases=ph, v_compared_120=v + 1.0, tap=tap)):
            out += aligner.add(k, f)
    assert [a.t_ns for a in out] == [T0, t1]  # two control steps: T0 (its period's one frame) and t1
    recent = out[1].vr_recent["vr1a"]
    assert [f.phases[0].v_120 for f in recent] == readings  # every recent frame; the window is the snapshot's
    model = synthetic_model(0)
    model = msgspec.structs.replace(model, regulators=[msgspec.structs.replace(model.regulators[0], id="vr1a")],
                                    pv=[msgspec.structs.replace(model.pv[0], id="pv1")])
    snap = snapshot_from(out[1], model)  # 5-minute window: the five frames after t1 - 300 s, all at tap 3
    assert snap.reg_v120[0] == pytest.approx(sum(readings[1:]) / 5)
    assert snapshot_from(out[1], model, reading_window_s=150).reg_v120[0] == pytest.approx(sum(readings[-3:]) / 3)
    assert snap.reg_v120_compared[0] == pytest.approx(sum(readings[1:]) / 5 + 1.0)
    assert snapshot_from(out[1], model, reading_window_s=600).reg_v120[0] == pytest.approx(sum(readings[1:]) / 5)
    last = snapshot_from(out[1], model, reading_window_s=0)
    assert last.reg_v120[0] == readings[-1]


def test_a_head_or_regulator_frame_lost_at_a_control_step_is_replaced_by_its_last_good_value(aligner):
    """A lost head frame at a control step made the step a hold (98 holds and
    NVV 446 in a rural winter week at 5 % lost frames); the latest one within ``last_good_s`` stands in."""
    from agent.runtime import AgentSettings
    from agent.snapshot import snapshot_from
    from benchmarks.synthetic import synthetic_model

    t1 = T0 + PERIOD_NS
    for i in range(1, 5):  # minutes T0+1 .. T0+4: every frame
        t = T0 + i * MINUTE
        for k, f in (head(t, i), pv(t, i), vr(t, i)):
            aligner.add(k, f)
    aligner.add(*pv(t1, 5))  # the control step's head and regulator frames are lost
    out = aligner.close_pending()
    assert [a.t_ns for a in out] == [t1] and set(out[0].missing) == {"head", "vr1a"}
    model = synthetic_model(0)
    model = msgspec.structs.replace(model, regulators=[msgspec.structs.replace(model.regulators[0], id="vr1a")],
                                    pv=[msgspec.structs.replace(model.pv[0], id="pv1")])
    snap = snapshot_from(out[0], model, last_good_s=AgentSettings(feeder_id="rural").last_good_s)
    assert snap.head_valid and snap.reg_valid[0]  # the frames of t1 - 60 s stand in
    assert not snap.head_fresh and not snap.reg_fresh[0]  # ... and are marked stale (the correction filter)
    assert snap.pv_fresh[0]  # the plant's own frame came
    assert snap.head_p_kw.sum() == pytest.approx(sum(p.p_kw for p in EX[m.HeadFrame].phases))
    old = snapshot_from(out[0], model, last_good_s=30)  # older than 30 s: not good any more
    assert not old.head_valid and not old.reg_valid[0]


def test_a_pv_frame_lost_at_a_control_step_is_replaced_by_its_last_good_value(aligner):
    """A plant whose frame was lost got no command; two in a row let its command expire, and it went back to unity
    power factor (NVV 188 in five minutes of a rural winter week at 5 % lost frames)."""
    from agent.snapshot import snapshot_from
    from benchmarks.synthetic import synthetic_model

    t1 = T0 + PERIOD_NS
    for k, f in (head(t1 - MINUTE, 1), pv(t1 - MINUTE, 1, p_kw=777.0), vr(t1 - MINUTE, 1)):
        aligner.add(k, f)
    out = [a for k, f in (head(t1, 2), vr(t1, 2)) for a in aligner.add(k, f)] + aligner.close_pending()
    assert [a.t_ns for a in out] == [t1] and out[0].missing == ("pv1",)
    model = synthetic_model(0)
    model = msgspec.structs.replace(model, regulators=[msgspec.structs.replace(model.regulators[0], id="vr1a")],
                                    pv=[msgspec.structs.replace(model.pv[0], id="pv1")])
    snap = snapshot_from(out[0], model, last_good_s=240)
    assert snap.pv_valid[0] and snap.pv_p_kw[0] == 777.0
    assert snap.head_fresh and not snap.pv_fresh[0]  # marked stale (the correction filter)
    assert snap.pv_age_s is not None and snap.pv_age_s[0] == 60.0  # its age (the stale-plant rule starts past 150 s)
    assert not snapshot_from(out[0], model, last_good_s=0).pv_valid[0]


@pytest.mark.parametrize("skew_ns", [2_000_000_000, -2_000_000_000])  # the field clocks 2 s ahead / behind
def test_frames_stamped_a_little_off_a_control_step_are_that_steps(skew_ns):
    tolerant = FrameAligner(feeder_id="rural", pv_ids=("pv1",), regulator_ids=("vr1a",), control_period_ns=PERIOD_NS,
                            clock_tolerance_ns=5_000_000_000)
    out = []
    for n in range(11):  # two control steps and the minutes between, every frame stamped skew_ns off
        t = T0 + n * MINUTE + skew_ns
        for k, f in (head(t, n + 1), pv(t, n + 1), vr(t, n + 1)):
            out += tolerant.add(k, f)
    assert [a.t_ns for a in out] == [T0, T0 + PERIOD_NS, T0 + 2 * PERIOD_NS]  # decided on the bridge's steps
    assert all(a.complete and a.head.t_ns == a.t_ns for a in out)
    assert tolerant.snapped == 9 and not tolerant.rejected  # 3 control steps x 3 frames; the minutes keep stamps
    strict = FrameAligner(feeder_id="rural", pv_ids=("pv1",), regulator_ids=("vr1a",), control_period_ns=PERIOD_NS)
    t = T0 + skew_ns
    assert [strict.add(k, f) for k, f in (head(t, 1), pv(t, 1), vr(t, 1))] == [[], [], []]  # never a decision


def test_a_step_end_stamped_off_the_step_still_releases_it():
    tolerant = FrameAligner(feeder_id="rural", pv_ids=("pv1",), regulator_ids=("vr1a",), control_period_ns=PERIOD_NS,
                            clock_tolerance_ns=5_000_000_000)
    t = T0 - 2_000_000_000
    tolerant.add(*head(t, 1))
    tolerant.add(*vr(t, 1))
    end = m.StepEnd(t_ns=t, seq=1, source="bridge", feeder_id="rural", head=True, pv=[], vr=["vr1a"], cap=[])
    (out,) = tolerant.add(keys.meas_step("rural"), end)
    assert out.t_ns == T0 and out.missing == ("pv1",)


@pytest.mark.parametrize("off_ns", [6_000_000_000, -30_000_000_000])
def test_frames_further_off_than_the_tolerance_keep_their_stamps(off_ns):
    tolerant = FrameAligner(feeder_id="rural", pv_ids=("pv1",), regulator_ids=("vr1a",), control_period_ns=PERIOD_NS,
                            clock_tolerance_ns=5_000_000_000)
    t = T0 + off_ns
    assert [tolerant.add(k, f) for k, f in (head(t, 1), pv(t, 1), vr(t, 1))] == [[], [], []]
    assert tolerant.snapped == 0


def test_a_clock_tolerance_of_half_a_period_is_refused():
    with pytest.raises(AgentInputError, match="half the control period"):
        FrameAligner(feeder_id="rural", pv_ids=("pv1",), regulator_ids=("vr1a",), control_period_ns=PERIOD_NS,
                     clock_tolerance_ns=PERIOD_NS // 2)


def test_the_snapshot_can_fit_the_regulator_readings_on_the_heads_load_and_move_them_to_the_present_tap(aligner):
    """``reading_fit_s`` (opt-in, agent/readings.py): readings that fall as the head's load rises, with a tap change
    half-way, give the present reading exactly, where the 5-minute mean lags the load."""
    from agent.snapshot import snapshot_from
    from benchmarks.synthetic import synthetic_model

    base, hbase = EX[m.RegFrame], EX[m.HeadFrame]
    out = []
    n = 30  # minutes; the last one is a control step
    t_end = T0 + 6 * PERIOD_NS
    for i in range(n):
        t = t_end - (n - 1 - i) * MINUTE
        p_total = 1000.0 + 40.0 * i
        phases = [msgspec.structs.replace(ph, p_kw=p_total / len(hbase.phases)) for ph in hbase.phases]
        tap = 2 if i < n // 2 else 3
        v = 126.0 - 0.002 * p_total + 0.75 * (tap - 3)
        ph = [msgspec.structs.replace(base.phases[0], v_120=v)]
        for k, f in (head(t, i + 1, phases=phases, p_kw=sum(x.p_kw for x in phases)), pv(t, i + 1),
                     vr(t, i + 1, phases=ph, v_compared_120=v, tap=tap)):
            out += aligner.add(k, f)
    assert out[-1].t_ns == t_end and len(out[-1].head_history) == n
    model = synthetic_model(0)
    model = msgspec.structs.replace(model, regulators=[msgspec.structs.replace(model.regulators[0], id="vr1a",
                                                                               step_v120=0.75)],
                                    pv=[msgspec.structs.replace(model.pv[0], id="pv1")])
    now = 126.0 - 0.002 * (1000.0 + 40.0 * (n - 1))
    fitted = snapshot_from(out[-1], model, reading_fit_s=3600)
    assert fitted.reg_v120[0] == pytest.approx(now, abs=1e-6)
    assert fitted.reg_v120_compared[0] == pytest.approx(now, abs=1e-6)
    assert snapshot_from(out[-1], model).reg_v120[0] == pytest.approx(now + 0.002 * 40.0 * 2)  # the mean lags 2 min
