"""uimm-est's first declaration: ``declare_rel`` (docs/faults.md, "Session 11"; 0.15 by default)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from uimm_jax.engine._est_rules import declarable
from uimm_jax.engine.uimm_est import EstSettings


def test_declare_rel_refuses_a_loose_estimate_only_while_nothing_is_declared():
    """With ``declare_rel`` a first declaration needs ``sd <= declare_rel * est`` as well as
    ``est >= declare_min``; once a fault is declared only ``declare_min`` counts."""
    # faults (valve wear, leakage) x runs: run 0 nothing declared, a tight leakage (sd 0.05
    # of 0.3); run 1 nothing declared, a loose one (0.09 of 0.3); run 2 nothing declared,
    # tight but below declare_min; run 3 valve wear declared, a loose leakage.
    declared = jnp.asarray([[False, False, False, True], [False, False, False, False]])
    est = jnp.asarray([[0.05, 0.05, 0.05, 0.5], [0.3, 0.3, 0.1, 0.3]])
    sd = jnp.asarray([[0.5, 0.5, 0.5, 0.01], [0.05, 0.09, 0.001, 0.09]])
    s = EstSettings(declare_rel_next=0.0)  # the later declarations' test apart
    on = declarable(s._replace(declare_rel=0.2), declared, est, sd)
    off = declarable(s._replace(declare_rel=0.0), declared, est, sd)
    np.testing.assert_array_equal(on[1], [True, False, False, True])
    np.testing.assert_array_equal(off[1], [True, True, False, True])
    np.testing.assert_array_equal(on[0], [False, False, False, True])


def test_declare_trend_refuses_an_estimate_projected_below_declare_min():
    """With ``declare_trend = H`` a new declaration also needs ``est + H min(trend, 0) >=
    declare_min`` (docs/faults.md, "Session 27"): a falling estimate is refused, a rising or
    steady one is not, and a declared fault is not a new declaration (``cand_set``)."""
    H, s = 500, EstSettings(declare_trend=500, declare_rel=0.0)
    # one fault x runs: falling fast (sim 2's leakage look-alike), falling slowly,
    # steady, rising, and falling fast from far above declare_min
    est = jnp.asarray([[0.19, 0.19, 0.19, 0.16, 0.5]])
    trend = jnp.asarray([[-2.2e-4, -5e-5, 0.0, 3e-4, -2.2e-4]])
    declared = jnp.zeros(est.shape, bool)
    sd = jnp.full(est.shape, 0.01)
    got = np.asarray(declarable(s, declared, est, sd, trend))
    want = np.asarray(est + H * np.minimum(trend, 0.0) >= s.declare_min)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got[0], [False, True, True, True, True])
    off = declarable(EstSettings(declare_rel=0.0, declare_trend=0), declared, est, sd, trend)
    np.testing.assert_array_equal(np.asarray(off[0]), [True] * 5)


def test_declare_rel_next_refuses_a_loose_estimate_only_while_a_fault_is_declared():
    """``declare_rel_next`` (session 27; 0.1 by default since session 32) is
    ``declare_rel`` for the later declarations: with a fault declared a new one needs
    ``sd <= declare_rel_next * est``; with nothing declared only ``declare_rel`` counts."""
    # faults (valve wear, leakage) x runs: valve wear declared in runs 0-2; leakage tight
    # (0.02 of 0.3), loose (0.03 of 0.3), loose but nothing declared (run 3)
    declared = jnp.asarray([[True, True, True, False], [False, False, False, False]])
    est = jnp.asarray([[0.5, 0.5, 0.5, 0.05], [0.3, 0.3, 0.37, 0.3]])
    sd = jnp.asarray([[0.01, 0.01, 0.01, 0.5], [0.02, 0.03, 0.039, 0.03]])
    s = EstSettings(declare_rel_next=0.08, declare_trend=0)
    got = np.asarray(declarable(s, declared, est, sd)[1])
    np.testing.assert_array_equal(got, [True, False, False, True])
    off = np.asarray(declarable(s._replace(declare_rel_next=0.0), declared, est, sd)[1])
    np.testing.assert_array_equal(off, [True, True, True, True])
    assert EstSettings().declare_rel_next == 0.1  # since session 32, with declare_rel_calm


def test_declare_rel_calm_holds_back_only_a_loose_estimate_of_a_slow_onset():
    """``declare_rel_calm`` (session 32): ``declare_rel_next`` acts only more than that many
    steps after model 0's last clear lead (``calm``): an abrupt fault's loose estimate,
    declared soon after the onset, passes; a slow onset's does not; a tight one always."""
    # faults (valve wear, leakage) x runs: valve wear declared; leakage loose (0.039 of
    # 0.37) soon after the onset, loose long after it, tight long after it, loose at the limit
    declared = jnp.asarray([[True] * 4, [False] * 4])
    est = jnp.asarray([[0.5] * 4, [0.37, 0.37, 0.37, 0.37]])
    sd = jnp.asarray([[0.01] * 4, [0.039, 0.039, 0.02, 0.039]])
    calm = jnp.asarray([120, 650, 650, 500])
    s = EstSettings(declare_rel_next=0.1, declare_rel_calm=500, declare_trend=0)
    got = np.asarray(declarable(s, declared, est, sd, None, calm)[1])
    np.testing.assert_array_equal(got, [True, False, True, True])
    every = np.asarray(declarable(s._replace(declare_rel_calm=0), declared, est, sd, None, calm)[1])
    np.testing.assert_array_equal(every, [False, False, True, False])
    without = np.asarray(declarable(s, declared, est, sd)[1])  # no counter: every one
    np.testing.assert_array_equal(without, every)


def test_onset_widen_frees_awake_hypotheses_fitted_to_noise_at_the_first_onset():
    """``onset_widen`` (session 31): in ``onset_restart``'s window while nothing is
    declared (model 0 does not lead, within ``onset_restart`` steps of its last clear
    lead), every undeclared hypothesis above ``restart_below`` that has not restarted
    within the window and does not lead keeps its estimate and gets a variance of at least
    ``prior_sd**2`` (its ``since`` to 1); the leader too while its estimate is within
    ``onset_widen`` sds of nominal (fitted to noise, not to the onset). One below
    ``restart_below`` restarts from the prior as always; nothing changes after a
    declaration, long after the lead, for a hypothesis restarted within the window, or
    with ``onset_widen`` 0."""
    import functools

    import jax

    from _robustness_helpers import short_dict
    from uimm_jax.engine import _est_rules as rules
    from uimm_jax.engine.imm import IMMState
    from uimm_jax.scenario.parse import parse_scenario
    from uimm_jax.studies.run import setup_scenario

    d = short_dict(2, duration=0.3)
    d["filter"].pop("initial_mode_probs")
    d["events"] = [{"time": 0.2, "fault": "valve_wear"}]
    diag = setup_scenario(parse_scenario(d), "uimm-est").diagnoser
    n, F, M = diag.dyn.n, diag.num_faults, diag.num_models
    s = diag.settings._replace(onset_widen=6.0)
    # runs: 0 nothing declared, leakage's hypothesis (model 2) leads 5 steps after model
    # 0's clear lead, 1.4 +- 0.4 (3.5 sds: within onset_widen); 1 the same 100 steps
    # after; 2 valve wear declared; 3 as 0 with valve wear's hypothesis restarted 10
    # steps ago; 4 as 0 with the leader at 1.4 +- 0.1 (14 sds: it fits the onset)
    R = 5
    declared = jnp.asarray([[False, False, True, False, False], [False] * R, [False] * R])
    calm = jnp.asarray([5, 100, 5, 5, 5], jnp.int32)
    mean = np.zeros((n + F, M, R))
    mean[n, 1] = 0.14  # valve wear's own hypothesis: awake, small, narrow
    mean[n + 1, 2] = 1.4  # leakage's, leading
    mean[n, :, 2] = 1.0  # run 2: valve wear declared, every model
    var = np.r_[np.full(n, 1e-4), 0.14**2, 0.4**2, 1.0]
    cov = np.broadcast_to(np.diag(var)[..., None, None], (n + F, n + F, M, R)).copy()
    cov[n + 1, n + 1, :, 4] = 0.1**2
    mu = np.array([[0.3] * R, [0.05] * R, [0.65] * R, [1e-5] * R])  # air in oil: below
    state = IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.log(jnp.asarray(mu)))
    use = diag.model_sets(declared)
    since = jnp.full((F, R), 1000, jnp.int32).at[0, 3].set(10)
    for z in (6.0, 0.0):
        on = z > 0
        reset = jax.jit(functools.partial(rules.reset_unused, s._replace(onset_widen=z), n))
        got, new_since = reset(state, use, declared, since, None, calm)
        gm, gv = np.asarray(got.mean), np.asarray(got.cov)
        # valve wear's hypothesis (runs 0 and 4; not run 3, restarted within the window)
        np.testing.assert_allclose(gm[n, 1, [0, 1, 3, 4]], 0.14)
        wide = [on, False, False, on]
        want = np.where(wide, s.prior_sd**2, 0.14**2)
        np.testing.assert_allclose(gv[n, n, 1, [0, 1, 3, 4]], want)
        np.testing.assert_array_equal(np.asarray(new_since[0, [0, 1, 3, 4]]) == 1, wide)
        # the leader, its estimate kept: widened in runs 0 and 3, not after a declaration
        # nor in run 4, where it lies 14 sds from nominal
        np.testing.assert_allclose(gm[n + 1, 2], 1.4)
        want = np.where([on, False, False, on, False], s.prior_sd**2, [0.4**2] * 4 + [0.1**2])
        np.testing.assert_allclose(gv[n + 1, n + 1, 2], want)
        # air in oil, below restart_below: from the prior in every run, as always
        np.testing.assert_allclose(gm[n + 2, 3], s.prior_mean)
