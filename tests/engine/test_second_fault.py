"""uimm-est with a second fault: the settings of docs/faults.md, "Session 9" (off by default)."""

from __future__ import annotations

import dataclasses

import numpy as np

from _robustness_helpers import short_dict
from uimm_jax.engine import _est_rules as rules
from uimm_jax.scenario.parse import parse_scenario


def _diag():
    from uimm_jax.studies.run import setup_scenario

    d = short_dict(2, duration=0.3)
    d["filter"].pop("initial_mode_probs")  # written for "uimm": the default for "uimm-est"
    d["events"] = [{"time": 0.2, "fault": "valve_wear"}]
    return setup_scenario(parse_scenario(d), "uimm-est").diagnoser


def test_walk_rel_newest_grows_the_walk_of_the_fault_declared_last_while_young():
    """With two faults declared, ``walk_rel_single`` grows neither walk; with
    ``walk_rel_newest`` (and ``walk_settled``) the younger fault's walk grows, until it is
    ``settle_steps`` old."""
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    diag = _diag()
    n, F, M = diag.dyn.n, diag.num_faults, diag.num_models
    base = diag.settings._replace(walk_settled=3e-4, settle_steps=100)
    mean = np.zeros((n + F, M, 3))
    mean[n : n + F, 0] = 2.0  # model 0's estimates
    cov = np.broadcast_to(np.eye(n + F)[..., None, None] * 0.01, (n + F, n + F, M, 3)).copy()
    state = IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.zeros((M, 3)))
    # runs: valve wear (age 150) + air in oil (age 20 / 120); air in oil alone (age 20)
    declared = jnp.asarray([[True, True, False], [False, False, False], [True, True, True]])
    since = jnp.asarray([[150, 150, 0], [0, 0, 0], [20, 120, 20]], jnp.int32)
    extra = (base.walk_rel * 2.0) ** 2 - base.walk**2
    assert base.walk_rel_single and extra > 0
    for newest, grown in ((False, [(2, 2)]), (True, [(2, 0), (2, 2)])):
        d2 = dataclasses.replace(diag, settings=base._replace(walk_rel_newest=newest))
        got = np.asarray(rules.walk_rel(d2.settings, d2.dyn.n, state, declared, since).cov) - cov
        want = np.zeros_like(cov)
        for j, r in grown:
            want[n + j, n + j, :, r] = extra  # every model's copy
        np.testing.assert_allclose(got, want, atol=1e-18)


def test_post_floor_mean_bounds_a_challenger_only_while_a_fault_is_declared():
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    diag = _diag()
    n, F, M = diag.dyn.n, diag.num_faults, diag.num_models
    mean = np.zeros((n + F, M, 2))
    cov = np.broadcast_to(np.eye(n + F)[..., None, None] * 0.01, (n + F, n + F, M, 2)).copy()
    state = IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.zeros((M, 2)))
    declared = jnp.asarray([[True, False], [False, False], [False, False]])  # run 0: valve wear
    s = diag.settings
    for post, want in ((0.0, [s.floor_mean] * 2), (0.02, [0.02, s.floor_mean])):
        d2 = dataclasses.replace(diag, settings=s._replace(post_floor_mean=post))
        got = np.asarray(
            rules.floor(d2.settings, d2.dyn.n, state, declared, jnp.zeros((F, 2), jnp.int32)).mean
        )
        np.testing.assert_allclose(got[n + 2, 3], want)  # air in oil's own hypothesis (slot 3)
        np.testing.assert_allclose(got[n + 1, 2], want)  # leakage's (slot 2)
        np.testing.assert_allclose(got[n, 1], [0.0, s.floor_mean])  # declared: untouched


def test_post_floor_means_bound_each_challenger_at_its_own_floor():
    """``post_floor_means``: one floor per fault while a fault is declared (session 10);
    with ``low_floor_age``, only once the declared fault is that old (before: the shared
    ``post_floor_mean``)."""
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    diag = _diag()
    n, F, M = diag.dyn.n, diag.num_faults, diag.num_models
    cov = np.broadcast_to(np.eye(n + F)[..., None, None] * 0.01, (n + F, n + F, M, 2)).copy()
    state = IMMState(jnp.zeros((n + F, M, 2)), jnp.asarray(cov), jnp.zeros((M, 2)))
    declared = jnp.asarray([[True, False], [False, False], [False, False]])  # run 0: valve wear
    s = diag.settings._replace(post_floor_mean=0.02, post_floor_means=(0.01, 0.03, 0.002))
    for age, low_age, own in ((0, 0, True), (99, 100, False), (100, 100, True)):
        since = jnp.full((F, 2), age, jnp.int32)
        d2 = dataclasses.replace(diag, settings=s._replace(low_floor_age=low_age))
        got = np.asarray(rules.floor(d2.settings, d2.dyn.n, state, declared, since).mean)
        air, leak = (0.002, 0.03) if own else (0.02, 0.02)
        np.testing.assert_allclose(got[n + 2, 3], [air, s.floor_mean])  # air in oil (slot 3)
        np.testing.assert_allclose(got[n + 1, 2], [leak, s.floor_mean])  # leakage (slot 2)
        np.testing.assert_allclose(got[n, 1], [0.0, s.floor_mean])  # declared: untouched
    # ``since`` must count that far (it stops at the largest gap), else the floors never hold
    from uimm_jax.engine._est_rules import gap_cap

    old = s._replace(walk_settled=3e-5, settle_steps=3000, low_floor_age=8000)
    assert gap_cap(old) == 8000 and gap_cap(old._replace(low_floor_age=0)) == 3000


def test_post_floor_means_needs_one_floor_per_fault():
    import pytest

    from uimm_jax.engine.uimm_est import EstSettings, build_diagnoser

    diag = _diag()
    bad = EstSettings(post_floor_means=(0.02, 0.002))
    msg = r"settings.post_floor_means: expected one floor per fault \(3"
    with pytest.raises(ValueError, match=msg):
        build_diagnoser("uimm-est", diag.dyn, diag.table, settings=bad)


def test_settle_move_restarts_a_fault_s_age_only_when_its_estimate_grows():
    """``settle_move``: a move of more than ``settle_move`` sd away from nominal restarts
    the age and re-anchors; a move towards nominal only re-anchors; a small move neither."""
    import jax.numpy as jnp

    from uimm_jax.engine._est_rules import moved
    from uimm_jax.engine.uimm_est import EstSettings

    s = EstSettings(walk_settled=3e-5, settle_steps=100, settle_move=5.0)
    # runs: grew (0.5 -> 0.6, sd 0.01), shrank (0.5 -> 0.4), small move, not declared
    declared = jnp.asarray([[True, True, True, False]])
    anchor = jnp.asarray([[0.5, 0.5, 0.5, 0.5]])
    est = jnp.asarray([[0.6, 0.4, 0.54, 0.9]])
    sd = jnp.full((1, 4), 0.01)
    since = jnp.asarray([[150, 150, 150, 150]], jnp.int32)
    new_since, new_anchor = moved(s, declared, est, sd, since, anchor)
    np.testing.assert_array_equal(new_since, [[0, 150, 150, 150]])
    np.testing.assert_allclose(new_anchor, [[0.6, 0.4, 0.5, 0.5]])


def test_retract_race_keeps_challengers_while_a_retraction_hypothesis_leads():
    """``retract_race``: while "D - f_j" leads, a challenger of low probability above its
    floor keeps its own estimate, one at its floor restarts; while model 0 leads both
    restart from the prior, as without the setting."""
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    diag = _diag()
    n, F, M = diag.dyn.n, diag.num_faults, diag.num_models
    declared = jnp.asarray([[True, True], [False, False], [False, False]])  # valve wear
    s = diag.settings
    mean = np.zeros((n + F, M, 2))
    mean[n : n + F] = 0.3
    mean[n + 1, 2] = s.floor_mean  # leakage's own hypothesis (slot 2): at its floor
    mean[n + 2, 3] = 2 * s.floor_mean  # air in oil's (slot 3): above it, below the prior
    cov = np.broadcast_to(np.eye(n + F)[..., None, None] * 1e-4, (n + F, n + F, M, 2)).copy()
    lp = np.log(np.full((M, 2), 1e-5))
    lp[1, 0] = lp[0, 1] = np.log(0.99)  # run 0: "D - valve wear" leads; run 1: D leads
    state = IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(lp))
    since = jnp.full((F, 2), 500, jnp.int32)
    use = diag.model_sets(declared)
    prior = [s.prior_mean, s.prior_mean]
    for on, air in ((False, prior), (True, [2 * s.floor_mean, s.prior_mean])):
        st, _ = rules.reset_unused(s._replace(retract_race=on), n, state, use, declared, since)
        np.testing.assert_allclose(np.asarray(st.mean)[n + 2, 3], air)
        np.testing.assert_allclose(np.asarray(st.mean)[n + 1, 2], prior)
