"""A PV plant behind a stale frame (``agent.stale_plants``): its P projected from the fresh plants, its Q from our
last command in force, and not moved towards a higher voltage; through the controller with default settings."""

import dataclasses

import numpy as np
import pytest

from agent.controller import STALE_PLANT_AGE_S, CvvcController, MeasurementSnapshot
from agent.runtime import AgentSettings
from agent.stale_plants import STALE_RISE_CAP_FACTOR, StalePlants, project_stale_p_kw, stale_rise_pu
from tests.agent.test_controller import HIGH, K, controller, snapshot

PERIOD_NS = 300 * 10**9


@pytest.mark.parametrize(
    ("p_then", "then", "now", "expected"),
    [
        (400.0, [500.0, 300.0], [1000.0, 600.0], 800.0),  # the group doubled: so does the plant
        (400.0, [500.0, 300.0], [250.0, 150.0], 200.0),  # halved
        (900.0, [500.0, 300.0], [1500.0, 900.0], 1000.0),  # tripled, but never past the rating (1000 kVA)
        (0.0, [0.0, 0.0], [500.0, 500.0], 250.0),  # dark then: the group's share of its rating (1000 of 4000)
    ],
)
def test_projection_follows_the_fresh_plants(p_then, then, now, expected):
    kva = np.array([2000.0, 2000.0])
    assert project_stale_p_kw(p_then, np.array(then), np.array(now), kva, 1000.0) == pytest.approx(expected)


def test_projection_needs_another_plant():
    assert project_stale_p_kw(400.0, np.zeros(0), np.zeros(0), np.zeros(0), 1000.0) is None


def test_a_command_is_in_force_for_two_periods_after_its_step():
    s = StalePlants(np.full(2, 1000.0), 2 * PERIOD_NS)
    s.commanded(0, np.array([-500.0, 100.0]), np.array([True, False]))
    assert np.isnan(s.commanded_q_kvar(0)).tolist() == [True, True]  # not before the next step
    np.testing.assert_allclose(s.commanded_q_kvar(PERIOD_NS), [-500.0, np.nan])
    np.testing.assert_allclose(s.commanded_q_kvar(2 * PERIOD_NS), [-500.0, np.nan])
    assert np.all(np.isnan(s.commanded_q_kvar(2 * PERIOD_NS + 1)))  # expired


def _with_p(t_ns: int, pv_p_kw: np.ndarray, **changes) -> MeasurementSnapshot:
    """``snapshot`` at 600 kW per plant with the plants' P frames replaced by ``pv_p_kw`` (K,) [kW]."""
    return dataclasses.replace(snapshot(t_ns, pv_p_kw=600.0), pv_p_kw=pv_p_kw, **changes)


def _default_controller(**kw) -> CvvcController:
    """The agent's controller with the default settings (as ``agent.runtime`` builds it), in taps mode."""
    s = AgentSettings()
    args = {"correction": s.correction, "correction_window_s": s.correction_window_s,
            "pv_margin_window_s": s.pv_margin_window_s, "sensitivity_error": s.sensitivity_error,
            "bounds_in_margin": s.bounds_in_margin, "stale_plants": s.stale_plants, **kw}
    return controller(**args)


def test_a_stale_plant_p_follows_the_fresh_plants_in_the_estimate():
    """pv0's frame is lost while the sky brightens (the fresh plants go from 600 to 1000 kW): the estimate takes
    pv0 at 1000 kW too, as if its own frame had come, not at its stale 600 kW."""
    fresh = np.array([False] + [True] * (K - 1))
    bright = np.full(K, 1000.0)
    seen = np.where(fresh, bright, 600.0)  # pv0's stand-in frame still says 600
    c, ref = _default_controller(correction=False), _default_controller(correction=False)
    for x in (c, ref):
        x.decide(snapshot(0, pv_p_kw=600.0))
    d = c.decide(_with_p(PERIOD_NS, seen, pv_fresh=fresh))
    own = ref.decide(_with_p(PERIOD_NS, bright))
    np.testing.assert_allclose(d.v_pu, own.v_pu, atol=1e-12)
    old = _default_controller(correction=False, stale_plants=False)
    old.decide(snapshot(0, pv_p_kw=600.0))
    assert not np.allclose(old.decide(_with_p(PERIOD_NS, seen, pv_fresh=fresh)).v_pu, own.v_pu, atol=1e-6)


def test_a_stale_plant_starts_from_our_command_and_is_not_raised():
    """Step 0 is over-voltage: pv2 absorbs. At step 1 the voltage is back and pv2's frame is a stand-in (Q 0, from
    before the command): the decision starts pv2 from the command it follows and does not raise it; without the rule
    it takes the frame's 0 kvar as where the plant is and leaves it there (a rise it does not count)."""
    c = _default_controller()
    d0 = c.decide(snapshot(0, reading_error_pu=HIGH))
    assert d0.pv_q_kvar[2] < -1.0, d0.pv_q_kvar  # absorbing
    fresh = np.array([True] * (K - 1) + [False])
    d1 = c.decide(snapshot(PERIOD_NS, pv_fresh=fresh))
    assert d1.status == "optimal" and d1.pv_command.all(), d1.reason
    assert d1.pv_q_kvar[2] <= d0.pv_q_kvar[2] + 1e-6
    old = _default_controller(stale_plants=False)
    old.decide(snapshot(0, reading_error_pu=HIGH))
    assert old.decide(snapshot(PERIOD_NS, pv_fresh=fresh)).pv_q_kvar[2] > d0.pv_q_kvar[2] + 1.0


def test_a_stale_plant_p_uncertainty_tightens_the_upper_limits():
    """pv0 stood at 1000 kW during the margin window and its stand-in frame says 200 kW: the upper limits come down
    by what pv0 would add going back to 1000 kW, up to 1.5 times the margin's cap, beyond the plain margin's cap."""
    rng = np.random.default_rng(1)
    dv_dp = rng.uniform(1e-6, 3e-5, (6, 3))
    recent = np.array([[1000.0, 500.0, 500.0], [1000.0, 500.0, 500.0]])
    p = np.array([200.0, 500.0, 500.0])
    cap = 0.01
    rise = np.minimum(dv_dp[:, 0] * 800.0, cap)  # the plain margin's, every plant (only pv0 moved)
    out = stale_rise_pu(rise, dv_dp, p, recent, np.array([True, False, False]), cap)
    np.testing.assert_allclose(out, np.minimum(rise + dv_dp[:, 0] * 800.0, STALE_RISE_CAP_FACTOR * cap))
    assert np.any(out > cap)
    np.testing.assert_allclose(stale_rise_pu(rise, dv_dp, p, recent, np.zeros(3, bool), cap), rise)


def test_a_stand_in_of_a_minute_is_taken_as_it_is():
    """A plant's stand-in frame one minute old (one frame dropped) is taken as it is, P and Q; one older than
    ``STALE_PLANT_AGE_S`` (an outage) is projected. 20 % of the frames lost at random made stand-ins of a minute at
    one step in five per plant, and the rule at each took the rural winter week from 20 to 144 tap changes."""
    fresh = np.array([False] + [True] * (K - 1))
    bright = np.full(K, 1000.0)
    seen = np.where(fresh, bright, 600.0)
    for age_s, projected in ((60.0, False), (STALE_PLANT_AGE_S + 60.0, True)):
        c, ref = _default_controller(correction=False), _default_controller(correction=False)
        for x in (c, ref):
            x.decide(snapshot(0, pv_p_kw=600.0))
        d = c.decide(_with_p(PERIOD_NS, seen, pv_fresh=fresh, pv_age_s=np.where(fresh, 0.0, age_s)))
        as_is = ref.decide(_with_p(PERIOD_NS, seen))
        same = bool(np.allclose(d.v_pu, as_is.v_pu, atol=1e-12))
        assert same is not projected, age_s
