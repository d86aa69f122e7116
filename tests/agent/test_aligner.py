"""The frame aligner: grouping by timestamp, the hold/missing rule, and every rejection reason."""

from __future__ import annotations

import msgspec
import pytest

from agent.aligner import FrameAligner
from schemas import keys
from schemas import messages as m
from schemas.examples import examples

PERIOD_NS = 300_000_000_000
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
    (out,) = aligner.close_pending()
    assert out.head is None and out.missing == ("head", "vr1a")


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
