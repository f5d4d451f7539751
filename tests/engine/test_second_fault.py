"""uimm-est with a second fault: the settings of docs/faults.md, "Session 9" and "Session 10".

Off by default until session 11 (the settings "S10a" are the defaults since); each test
states the settings it compares.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from _robustness_helpers import short_dict
from uimm_jax.engine import _est_rules as rules
from uimm_jax.scenario.parse import parse_scenario


def _setup():
    from uimm_jax.studies.run import setup_scenario

    d = short_dict(2, duration=0.3)
    d["filter"].pop("initial_mode_probs")  # written for "uimm": the default for "uimm-est"
    d["events"] = [{"time": 0.2, "fault": "valve_wear"}]
    return setup_scenario(parse_scenario(d), "uimm-est")


def _diag():
    return _setup().diagnoser


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
    s = diag.settings._replace(post_floor_means=())  # one floor for all (the tuned file's: 3)
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

    old = s._replace(walk_settled=3e-5, settle_steps=3000, low_floor_age=8000, retract_young=0)
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


def test_settle_low_lowers_only_a_declaration_s_anchor_on_the_step_it_settles():
    """``settle_low`` (session 13): on the step a declared fault settles (age
    ``settle_steps``), an anchor still at its declaration's value comes down to an estimate
    nearer nominal (and is no longer the declaration's); nothing else moves."""
    import jax.numpy as jnp

    from uimm_jax.engine.uimm_est import EstSettings

    s = EstSettings(walk_settled=3e-5, settle_steps=100, settle_move=5.0, settle_low=True)
    # runs: settling with the declaration's anchor above the estimate / below it, settling
    # with an anchor set by a move, settled long ago, still young, a negative magnitude
    # settling, not declared
    declared = jnp.asarray([[True] * 6 + [False]])
    since = jnp.asarray([[100, 100, 100, 150, 50, 100, 100]], jnp.int32)
    anchor = jnp.asarray([[0.5] * 5 + [-0.5, 0.5]])
    fresh = jnp.asarray([[True, True, False, True, True, True, True]])
    est = jnp.asarray([[0.45, 0.55, 0.45, 0.45, 0.45, -0.45, 0.45]])
    new_anchor, new_fresh = rules.settle_low(s, declared, est, since, anchor, fresh)
    np.testing.assert_allclose(new_anchor, [[0.45, 0.5, 0.5, 0.5, 0.5, -0.45, 0.5]])
    np.testing.assert_array_equal(new_fresh, [[False, True, False, True, True, False, True]])


def test_settle_creep_moves_only_a_settled_anchor_and_only_away_from_nominal():
    """``settle_creep`` (session 14): a settled declared fault's anchor moves ``1 /
    settle_creep`` of the way to an estimate farther from nominal while it is the only
    declared fault; an estimate nearer nominal, a young fault, an undeclared one or one
    declared beside another leave it alone."""
    import jax.numpy as jnp

    from uimm_jax.engine.uimm_est import EstSettings

    s = EstSettings(walk_settled=3e-5, settle_steps=100, settle_move=5.0, settle_creep=4)
    # runs: settled with the estimate above the anchor, below it, young, negative magnitude
    # above in size, not declared, settled beside another declared fault (second row)
    declared = jnp.asarray([[True] * 4 + [False, True], [False] * 5 + [True]])
    since = jnp.asarray([[100, 150, 50, 120, 150, 150]] * 2, jnp.int32)
    anchor = jnp.asarray([[0.5, 0.5, 0.5, -0.5, 0.5, 0.5]] * 2)
    est = jnp.asarray([[0.6, 0.4, 0.6, -0.7, 0.6, 0.6]] * 2)
    new_anchor = rules.settle_creep(s, declared, est, since, anchor)
    np.testing.assert_allclose(new_anchor[0], [0.525, 0.5, 0.5, -0.55, 0.5, 0.5])
    np.testing.assert_allclose(new_anchor[1], anchor[1])  # fault 1: never alone


def test_retract_young_holds_an_old_fault_s_retraction_only_while_another_grows():
    """``retract_young`` (session 14): a declared fault that has not grown for
    ``retract_young`` steps (its age ``since``) is held back from a retraction by its
    hypothesis while another declared fault is younger than that; a lone fault, two old
    ones, or a fault that is young itself (settled, but declared or grown lately: a new
    fault that ends while the older ones' estimates moved at its onset) is not, and 0
    turns the rule off (``gap_cap`` then as before)."""
    import jax.numpy as jnp

    from uimm_jax.engine.uimm_est import EstSettings

    s = EstSettings(settle_steps=100, retract_young=1000, low_floor_age=500)
    # runs: old + young, both old, settled but young + young, one declared and old (an
    # intermittent fault), a young third fault undeclared
    declared = jnp.asarray(
        [
            [True, True, True, True, True],
            [True, True, True, False, False],
            [False, False, False, False, False],
        ]
    )
    since = jnp.asarray(
        [[1000, 1000, 500, 1000, 1000], [300, 1000, 50, 10, 1000], [9, 9, 9, 9, 9]], jnp.int32
    )
    held = rules.retract_young(s, declared, since)
    want = [[True, False, False, False, False], [False, False, False, False, False], [False] * 5]
    np.testing.assert_array_equal(held, want)
    assert rules.gap_cap(s) == 1000  # since counts far enough to see the other grow
    assert rules.gap_cap(s._replace(retract_young=0)) == 500  # low_floor_age, as before


def test_retract_keep_keeps_only_the_challenger_that_led_before_the_retraction_hypothesis():
    """``retract_keep`` (session 12): while "D - f_j" leads, the undeclared hypothesis that
    led just before it does not restart at its floor; the others do, and so does it once
    model 0 has led in between.  A restart for low probability is left alone."""
    import functools

    import jax
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    diag = _diag()
    n, F, M = diag.dyn.n, diag.num_faults, diag.num_models
    declared = jnp.asarray([[True], [False], [False]])  # valve wear declared (one run)
    chal = jnp.zeros((1,), jnp.int32)
    # leaders in turn: air in oil's hypothesis (slot 3), "D - valve wear" (slot 1), model 0
    # then slot 1 again, leakage's hypothesis (slot 2) then slot 1
    wants = [(3, 3, []), (1, 3, [2]), (1, 3, [2]), (0, 0, []), (1, 0, []), (2, 2, []), (1, 2, [1])]
    challenger = jax.jit(rules.challenger)  # one compilation, not one per eager operation
    for lead, want_chal, want_keep in wants:
        log_mu = np.log(np.where(np.arange(M) == lead, 0.97, 0.01))[:, None]
        keep, chal = challenger(declared, log_mu, chal)
        assert int(chal[0]) == want_chal
        np.testing.assert_array_equal(np.nonzero(np.asarray(keep[:, 0]))[0], want_keep)
    # reset_unused: air in oil's hypothesis at its floor, leakage's at low probability:
    # the kept air in oil keeps its estimate, leakage restarts from the prior either way
    s = diag.settings._replace(retract_keep=True, post_floor_means=(), post_floor_mean=0.02)
    mean = np.zeros((n + F, M, 1))
    mean[n, :, 0] = 0.3  # valve wear's estimate in every model
    mean[n + 1, 2, 0], mean[n + 2, 3, 0] = 0.2, 0.02  # leakage's and air in oil's own
    cov = np.broadcast_to(np.eye(n + F)[..., None, None] * 1e-4, (n + F, n + F, M, 1)).copy()
    log_mu = jnp.log(jnp.asarray([[0.01], [0.98], [1e-5], [0.01]]))
    state = IMMState(jnp.asarray(mean), jnp.asarray(cov), log_mu)
    use = diag.model_sets(declared)
    since = jnp.full((F, 1), 1000, jnp.int32)
    reset = jax.jit(functools.partial(rules.reset_unused, s, n))
    for kept, air in ((True, 0.02), (False, s.prior_mean)):
        keep = jnp.asarray([[False], [False], [kept]])
        got, _ = reset(state, use, declared, since, keep)
        np.testing.assert_allclose(np.asarray(got.mean[n + 2, :, 0]), air)  # every model
        np.testing.assert_allclose(np.asarray(got.mean[n + 1, :, 0]), s.prior_mean)  # leakage


def test_reopen_old_widens_the_faults_kept_only_on_a_step_that_declares_another():
    """``reopen_old`` (session 15): on a declaration the newly declared fault's sd is
    raised to ``reopen_rel`` of its mean and every fault that stays declared to
    ``reopen_old`` of its own, in every model; a wider sd is kept, the means and every
    other entry of the covariance are unchanged (a PSD matrix is added), and with
    ``reopen_old = 0`` the kept faults are left alone."""
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState
    from uimm_jax.engine.uimm_est import EstSettings

    n, F, M, R = 3, 3, 4, 2
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(n + F, M, R))
    mean[n:] = np.abs(mean[n:]) + 1.0
    a = rng.normal(size=(n + F, n + F, M, R))
    cov = np.einsum("ikmr,jkmr->ijmr", a, a) * 1e-6 + np.eye(n + F)[..., None, None] * 1e-8
    st = IMMState(log_mode_probs=jnp.zeros((M, R)), mean=jnp.asarray(mean), cov=jnp.asarray(cov))
    # run 0: fault 2 newly declared, fault 0 kept (declared before), fault 1 not declared;
    # run 1: nothing new (no kept fault either)
    new = jnp.asarray([[False, False], [False, False], [True, False]])
    kept = jnp.asarray([[True, False], [False, False], [False, False]])
    s = EstSettings(reopen_rel=0.2, reopen_old=0.01)
    out = rules.reopen(s, n, st, new, kept)
    np.testing.assert_array_equal(out.mean, st.mean)
    var_in = np.asarray(rules.mag_var(st.cov, n))
    var_out = np.asarray(rules.mag_var(out.cov, n))
    np.testing.assert_allclose(
        var_out[2, :, 0], np.maximum((0.2 * mean[n + 2, :, 0]) ** 2, var_in[2, :, 0])
    )
    np.testing.assert_allclose(
        var_out[0, :, 0], np.maximum((0.01 * mean[n, :, 0]) ** 2, var_in[0, :, 0])
    )
    assert np.all(var_out[0, :, 0] > var_in[0, :, 0])  # (0.01 x mean >= 1)^2 > these variances
    np.testing.assert_array_equal(var_out[1], var_in[1])
    np.testing.assert_array_equal(var_out[:, :, 1], var_in[:, :, 1])
    diff = np.asarray(out.cov) - cov
    off = ~np.eye(n + F, dtype=bool)
    np.testing.assert_array_equal(diff[off], 0.0)  # only the magnitudes' variances move
    off_rule = rules.reopen(s._replace(reopen_old=0.0), n, st, new, kept)
    np.testing.assert_array_equal(rules.mag_var(off_rule.cov, n)[0], var_in[0])


def test_retract_rise_counts_how_long_a_retraction_hypothesis_has_been_high():
    """``retract_rise`` (session 15): ``rise`` counts the steps each declared fault's
    retraction hypothesis (model ``i + 1``) has stayed at or above ``RISE_LEVEL``, up to
    ``retract_rise + 1``; it restarts at 0 below the level or when the fault is not
    declared, so a hypothesis that jumped to the lead (a fault that ended) is told from one
    that climbed for long (another fault's lag)."""
    import jax.numpy as jnp

    from uimm_jax.engine.uimm_est import EstSettings

    s = EstSettings(retract_rise=3)
    declared = jnp.asarray([[True, True, False], [True, True, True]])  # (F=2, runs=3)
    p = np.array([[0.5, 0.5, 0.5], [0.2, 0.005, 0.3], [0.3, 0.495, 0.2]])  # (M=3, runs)
    lp = jnp.log(jnp.asarray(p))
    count = jnp.zeros((2, 3), jnp.int32)
    seen = []
    for _ in range(5):
        count = rules.rise(s, declared, lp, count)
        seen.append(np.asarray(count))
    # fault 0's hypothesis (model 1): high in runs 0 and 2, but run 2 has it undeclared
    np.testing.assert_array_equal(
        [c[0] for c in seen], [[1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0], [4, 0, 0]]
    )
    # fault 1's hypothesis (model 2): high in every run, declared in every run
    np.testing.assert_array_equal(seen[-1][1], [4, 4, 4])
    below = jnp.log(jnp.asarray(np.array([[0.99] * 3, [0.005] * 3, [0.005] * 3])))
    np.testing.assert_array_equal(rules.rise(s, declared, below, count), 0)  # restarts
    assert rules.RISE_LEVEL == 0.01


def test_floor_z_restarts_a_hypothesis_resting_near_its_floor_only_while_a_fault_is_declared():
    """``floor_z`` (session 16): while every declared fault has settled, an undeclared
    hypothesis whose estimate is within ``floor_z`` sds of its floor and whose probability
    is below ``NEAR_FLOOR_MU`` counts as held at the floor and restarts from the prior (at
    most every ``post_floor_gap`` steps), though its probability is above
    ``restart_below``; with ``floor_z = 0`` only one at the floor does, and while nothing
    is declared the floor is the plain one."""
    import functools

    import jax
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    diag = _diag()
    n, F, M = diag.dyn.n, diag.num_faults, diag.num_models
    base = diag.settings._replace(post_floor_means=(), post_floor_mean=0.02, floor_mean=0.05)
    # runs: air in oil declared (0, 1, 3: valve wear's own hypothesis at 0.049, 0.15 and
    # 0.049, sd 0.038; run 3 with probability 0.3) and nothing declared (2: at 0.06)
    declared = jnp.asarray([[False] * 4, [False] * 4, [True, True, False, True]])
    mean = np.zeros((n + F, M, 4))
    mean[n + 2, :, [0, 1, 3]] = 1.0  # air in oil's estimate, every model
    mean[n, 1] = [0.049, 0.15, 0.06, 0.049]  # valve wear's own hypothesis (slot 1)
    mean[n + 1, 2] = 0.5  # leakage's, far from its floor
    var = np.full(F, 1e-4)
    var[0] = 0.038**2
    cov = np.broadcast_to(
        np.diag(np.r_[np.full(n, 1e-4), var])[..., None, None], (n + F, n + F, M, 4)
    ).copy()
    mu = np.array([[0.9] * 3 + [0.65], [0.05] * 3 + [0.3], [0.04] * 4, [0.01] * 4])
    assert rules.NEAR_FLOOR_MU == 0.2
    state = IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.log(jnp.asarray(mu)))
    use = diag.model_sets(declared)
    restarted = {}
    s0 = base._replace(post_floor_gap=200, settle_steps=3000)
    assert rules.growth_ages(s0)  # a declared fault's ``since`` is its age
    cases = [(0.0, 1000, 5000), (2.0, 1000, 5000), (2.0, 10, 5000), (2.0, 1000, 100)]
    for z, age, air_age in cases:
        # since: the hypotheses' steps since their last restart (beyond post_floor_gap or
        # not), air in oil's age (settled, or grown within settle_steps)
        s = s0._replace(floor_z=z)
        reset = jax.jit(functools.partial(rules.reset_unused, s, n))
        since = jnp.asarray([[age] * 4, [age] * 4, [air_age] * 4], jnp.int32)
        got, new_since = reset(state, use, declared, since)
        again = np.isclose(np.asarray(got.mean[n, 1]), s.prior_mean)
        np.testing.assert_array_equal(np.asarray(new_since[0]) == 1, again)
        np.testing.assert_allclose(np.asarray(got.mean[n + 1, 2]), 0.5)  # leakage kept
        restarted[z, age, air_age] = again.tolist()
    assert restarted[0.0, 1000, 5000] == [False] * 4
    assert restarted[2.0, 1000, 5000] == [True, False, False, False]  # 0.049 <= 0.02 + 2 x 0.038
    assert restarted[2.0, 10, 5000] == [False] * 4  # not before post_floor_gap
    assert restarted[2.0, 1000, 100] == [False] * 4  # not while air in oil still grows


def test_onset_restart_restarts_the_resting_hypotheses_when_model_0_loses_a_clear_lead():
    """``onset_restart`` (session 26): while model 0 does not lead, within
    ``onset_restart`` steps of its probability last being at least ``ONSET_CALM`` at a
    step's start (``calm``) and while a fault is declared, every undeclared hypothesis that
    does not lead, has probability below ``NEAR_FLOOR_MU`` and has not restarted within
    ``onset_restart`` steps restarts from the prior (its ``since`` to 1), wherever its
    estimate is; the leader, a hypothesis at or above ``NEAR_FLOOR_MU``, one restarted
    within the window, every hypothesis while nothing is declared, while model 0 leads or
    long after its clear lead, and every one with ``onset_restart = 0``, keep their
    estimates (``onset_widen``, off here, acts while nothing is declared: tested in
    test_first_declaration.py).  ``step`` counts ``calm`` from the carried mode
    probabilities."""
    import functools

    import jax
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    diag = _diag()
    n, F, M = diag.dyn.n, diag.num_faults, diag.num_models
    s = diag.settings
    assert s.onset_restart == 20 and rules.NEAR_FLOOR_MU == 0.2  # the defaults
    # runs: valve wear declared, air in oil's hypothesis (model 3) leads: 0 five steps
    # after model 0's clear lead, 1 a hundred steps after, 2 with leakage's hypothesis at
    # 0.25; 3 nothing declared; 4 valve wear declared and model 0 leading; 5 as 0 with
    # leakage's hypothesis restarted 10 steps ago
    R = 6
    declared = jnp.asarray([[True, True, True, False, True, True], [False] * R, [False] * R])
    calm = jnp.asarray([5, 100, 5, 5, 0, 5], jnp.int32)
    mean = np.zeros((n + F, M, R))
    mean[n] = 1.0  # valve wear, every model
    mean[n + 1, 2] = 0.5  # leakage's own hypothesis: far from its floor (sd 0.1)
    mean[n + 2, 3] = 1.2  # air in oil's, leading
    var = np.r_[np.full(n, 1e-4), 1e-4, 0.01, 0.04]
    cov = np.broadcast_to(np.diag(var)[..., None, None], (n + F, n + F, M, R)).copy()
    mu = np.array([[0.3] * R, [0.05] * R, [0.05] * R, [0.6] * R])
    mu[:, 2] = [0.1, 0.05, 0.25, 0.6]
    mu[:, 4] = [0.7, 0.05, 0.05, 0.2]
    state = IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.log(jnp.asarray(mu)))
    use = diag.model_sets(declared)
    since = jnp.full((F, R), 1000, jnp.int32).at[1, 5].set(10)
    for window in (20, 0):
        s1 = s._replace(onset_restart=window, onset_widen=0.0)  # run 3: onset_widen's
        reset = jax.jit(functools.partial(rules.reset_unused, s1, n))
        got, new_since = reset(state, use, declared, since, None, calm)
        again = np.isclose(np.asarray(got.mean[n + 1, 2]), s.prior_mean)
        np.testing.assert_array_equal(np.asarray(new_since[1]) == 1, again)
        want = [window > 0, False, False, False, False, False]
        assert again.tolist() == want, (window, again)
        np.testing.assert_allclose(np.asarray(got.mean[n + 2, 3]), 1.2)  # the leader kept
        np.testing.assert_allclose(np.asarray(got.mean[n + 1, 2])[~np.asarray(want)], 0.5)
    # calm in a step: 0 while model 0 starts a step at >= 0.9, else one more (to the cap)
    params = _setup().params
    st = diag.init(np.zeros(n), np.eye(n), [0.95, 0.05 / 3, 0.05 / 3, 0.05 / 3], runs=(3,))
    assert np.all(np.asarray(st.calm) == rules.CALM_CAP)
    lp = np.log(np.array([[0.95, 0.5, 0.5], [0.02, 0.3, 0.3], [0.02, 0.1, 0.1], [0.01, 0.1, 0.1]]))
    st = st._replace(imm=st.imm._replace(log_mode_probs=jnp.asarray(lp)))
    st = st._replace(calm=jnp.asarray([7, 7, rules.CALM_CAP], jnp.int32))
    z = jnp.zeros((3, 3))
    new, _ = jax.jit(diag.step)(st, params, jnp.zeros((1, 3)), z)
    np.testing.assert_array_equal(np.asarray(new.calm), [0, 8, rules.CALM_CAP])


def test_restore_old_gives_a_kept_fault_its_level_back_only_on_a_clear_drop():
    """``restore_old`` (session 19): ``peak`` keeps each declared fault's level (the
    declaration's estimate, then the anchor's high-water mark, or an anchor brought down on
    the settle step) with its sd then; on a declaration, ``restore`` sets a kept fault's
    mean to its level in every model when the estimate lies more than ``restore_old`` of
    its sds and ``LEVEL_Z`` of the level's sds nearer nominal; nothing else moves."""
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState
    from uimm_jax.engine.uimm_est import EstSettings

    s = EstSettings(settle_steps=100, restore_old=10.0, restore_steps=50)
    # peak, runs: declared now, anchor raised above the level, anchor lowered by a move,
    # anchor lowered on the settle step (settle_low), anchor raised but below the level
    fresh = jnp.asarray([[True, False, False, False, False]])
    est = jnp.asarray([[1.5, 2.1, 1.6, 1.7, 1.8]])
    sd = jnp.asarray([[0.3, 0.01, 0.005, 0.004, 0.02]])
    since = jnp.asarray([[0, 0, 500, 100, 0]], jnp.int32)
    start = jnp.asarray([[0.0, 1.9, 2.0, 1.9, 1.5]])
    anchor = jnp.asarray([[1.5, 2.1, 1.6, 1.7, 1.8]])
    level = jnp.asarray([[0.0, 2.0, 2.0, 1.9, 2.0]])
    level_sd = jnp.asarray([[0.0, 0.02, 0.02, 0.2, 0.02]])
    lv, lsd = rules.peak(s, fresh, est, sd, since, start, anchor, level, level_sd)
    np.testing.assert_allclose(lv, [[1.5, 2.1, 2.0, 1.7, 2.0]])
    np.testing.assert_allclose(lsd, [[0.3, 0.01, 0.02, 0.004, 0.02]])
    # restore, runs: a clear drop, a drop of 5 sds only, a drop within 2 sds of a loose
    # level, a fault not kept, a negative magnitude's clear drop, a clear drop from a
    # level left 50 steps ago
    n, F, M, R = 3, 1, 2, 6
    rng = np.random.default_rng(1)
    mean = rng.normal(size=(n + F, M, R))
    a = rng.normal(size=(n + F, n + F, M, R))
    cov = np.einsum("ikmr,jkmr->ijmr", a, a)
    st = IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.zeros((M, R)))
    kept = np.asarray([[True, True, True, False, True, True]])
    est = np.asarray([[1.6, 1.97, 1.8, 1.6, -1.6, 1.6]])
    est_sd = np.full((1, R), 0.006)
    level = np.asarray([[2.0, 2.0, 2.0, 2.0, -2.0, 2.0]])
    level_sd = np.asarray([[0.01, 0.01, 0.1, 0.01, 0.01, 0.01]])
    left = np.asarray([[49, 0, 0, 0, 3, 50]], np.int32)
    args = (jnp.asarray(v) for v in (kept, est, est_sd, level, level_sd, left))
    out, back = rules.restore(s, n, st, *args)
    drop = np.abs(level) - np.abs(est)
    want_back = kept & (drop > 10.0 * est_sd) & (drop > rules.LEVEL_Z * level_sd) & (left < 50)
    np.testing.assert_array_equal(back, want_back)
    np.testing.assert_array_equal(want_back, [[True, False, False, False, True, False]])
    # level_left: 0 while the estimate is within LEVEL_Z sds of its level, else counting
    # up to restore_steps + 1
    got = rules.level_left(s, *(jnp.asarray(v) for v in (est, est_sd, level, level_sd, left)))
    near = drop <= rules.LEVEL_Z * np.maximum(est_sd, level_sd)
    np.testing.assert_array_equal(got, np.where(near, 0, np.minimum(left + 1, 51)))
    np.testing.assert_array_equal(got, [[50, 1, 0, 1, 4, 51]])
    want = mean.copy()
    want[n:] = np.where(want_back[:, None], level[:, None], mean[n:])
    np.testing.assert_array_equal(out.mean, want)
    np.testing.assert_array_equal(out.cov, cov)


def test_declare_trend_is_each_estimates_clipped_average_move_after_its_wait():
    """``EstState.trend`` (``declare_trend``, session 27) over 0.3 s of sim 2 with valve wear
    at 0.2 s: each step it is ``trend + (clip(est - before) - trend) / W`` (``W =
    trend_steps``, ``before`` the estimate at the cycle's start: the last step's for a
    hypothesis that did not restart), 0 for an undeclared hypothesis within ``W`` steps of
    its restart, and with ``declare_trend = 0`` it stays 0."""
    import jax
    import jax.numpy as jnp

    from uimm_jax.engine import _est_drift as drift_rules
    from uimm_jax.studies.run import simulate_scenario

    setup = _setup()
    diag, params = setup.diagnoser, setup.params
    s = diag.settings
    W = drift_rules.trend_steps(s)
    assert (s.declare_trend, W) == (500, 100)  # the default
    data = simulate_scenario(setup, seed=0)
    xs = (jnp.asarray(data["u"]), jnp.asarray(data["y"]))

    def run(d):
        def body(st, uy):
            st2, info = d.step(st, params, uy[0], uy[1], with_cov=False)
            return st2, (st2.trend, st2.since, st2.declared, info.magnitude)

        return jax.jit(lambda s0: jax.lax.scan(body, s0, xs)[1])(setup.init_state)

    trend, since, declared, est = map(np.asarray, run(diag))
    assert declared[-1].any()  # valve wear is declared: the run covers both phases
    young = ~declared & (since < W)
    assert np.all(trend[young] == 0.0) and (~young).any()
    # where nothing restarted at step k, the average takes the estimate's clipped move
    k = np.arange(1, len(trend))
    kept = (since[k] == since[k - 1] + 1) & ~young[k] & (declared[k] == declared[k - 1])
    move = np.clip(est[k] - est[k - 1], -drift_rules.DRIFT_CLIP, drift_rules.DRIFT_CLIP)
    want = trend[k - 1] + (move - trend[k - 1]) / W
    assert kept.sum() > 1000
    np.testing.assert_allclose(trend[k][kept], want[kept], rtol=1e-9, atol=1e-15)
    assert np.abs(trend).max() > 0
    off = np.asarray(run(dataclasses.replace(diag, settings=s._replace(declare_trend=0)))[0])
    assert np.all(off == 0.0)


def test_decl_restart_restarts_the_resting_hypotheses_after_a_declaration():
    """``decl_restart`` (session 28): while a declared fault's ``decl_age`` is below it,
    every undeclared hypothesis that does not lead and has probability below
    ``NEAR_FLOOR_MU`` restarts from the prior (its ``since`` to 1), wherever its estimate
    is; long after the declaration, with nothing declared, for a hypothesis at or above
    ``NEAR_FLOOR_MU``, for the leader and with ``decl_restart = 0`` estimates are kept.
    ``decl_age`` counts to ``max(retract_after, decl_restart)`` and starts there."""
    import functools

    import jax
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    diag = _diag()
    n, F, M = diag.dyn.n, diag.num_faults, diag.num_models
    s = diag.settings._replace(onset_restart=0)
    # runs: valve wear declared 5 steps ago; 1000 steps ago; 5 ago with leakage's
    # hypothesis at 0.3; nothing declared; 5 ago with leakage's hypothesis leading
    R = 5
    declared = jnp.asarray([[True, True, True, False, True], [False] * R, [False] * R])
    age = jnp.asarray([[5, 1000, 5, 5, 5], [4000] * R, [4000] * R], jnp.int32)
    mean = np.zeros((n + F, M, R))
    mean[n] = 1.0  # valve wear, every model
    mean[n + 1, 2] = 0.5  # leakage's own hypothesis: far from its floor (sd 0.1)
    mean[n + 2, 3] = 1.2  # air in oil's
    var = np.r_[np.full(n, 1e-4), 1e-4, 0.01, 0.04]
    cov = np.broadcast_to(np.diag(var)[..., None, None], (n + F, n + F, M, R)).copy()
    mu = np.array([[0.8] * R, [0.05] * R, [0.1] * R, [0.05] * R])
    mu[:, 2] = [0.6, 0.05, 0.3, 0.05]
    mu[:, 4] = [0.3, 0.05, 0.6, 0.05]
    state = IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.log(jnp.asarray(mu)))
    use = diag.model_sets(declared)
    since = jnp.full((F, R), 1000, jnp.int32)
    for window in (200, 0):
        reset = jax.jit(functools.partial(rules.reset_unused, s._replace(decl_restart=window), n))
        got, new_since = reset(state, use, declared, since, None, None, age)
        again = np.isclose(np.asarray(got.mean[n + 1, 2]), s.prior_mean)
        np.testing.assert_array_equal(np.asarray(new_since[1]) == 1, again)
        assert again.tolist() == [window > 0, False, False, False, False], (window, again)
        np.testing.assert_allclose(np.asarray(got.mean[n + 1, 2])[~again], 0.5)
    # the age: from the cap, 0 at a declaration, one more each step up to the cap
    for after, restart in ((0, 200), (4000, 200), (100, 300)):
        s1 = s._replace(retract_after=after, decl_restart=restart)
        cap = max(after, restart)
        assert rules.age_cap(s1) == cap
        fresh = jnp.asarray([[True, False, False]])
        a = jnp.full((1, 3), cap, jnp.int32).at[0, 1].set(cap - 1).at[0, 2].set(7)
        got = np.asarray(rules.declaration_age(s1, a, fresh))
        np.testing.assert_array_equal(got, [[0, cap, 8]])
