"""Faults as they really come: magnitudes on one scale, ramps and ends in the truth."""

from __future__ import annotations

import numpy as np
import pytest

from _engine_helpers import biased_sensors_dict
from _robustness_helpers import short_dict, with_est_settings
from uimm_jax.engine import _est_rules as rules
from uimm_jax.engine.bank import fault_table, param_at_magnitude
from uimm_jax.engine.truth import RAMP_SEGMENTS, fault_breakpoints, plan_phases
from uimm_jax.scenario.parse import parse_scenario
from uimm_jax.scenario.sweep import sweep_spec


def test_param_at_magnitude_log_and_linear_scales():
    for a in (0.0, 0.3, 1.0, 2.0, 3.0):
        assert param_at_magnitude(6e6, 6e5, a, True, np) == pytest.approx(6e6 * 0.1**a, rel=1e-13)
        assert param_at_magnitude(1e-10, 5e-9, a, False, np) == pytest.approx(
            1e-10 + a * 4.9e-9, rel=1e-13
        )
    # magnitude 1 is the library value bit for bit on both scales
    assert param_at_magnitude(6e6, 6e5, 1.0, True, np) == 6e5
    assert param_at_magnitude(2.7, 2.95, 1.0, True, np) == 2.95


def test_fault_table_refuses_a_log_parameter_that_is_not_positive():
    with pytest.raises(ValueError, match="log magnitude scale"):
        fault_table(("a",), np.ones(1), {"f": {"a": -1.0}}, log_params=("a",))


def test_breakpoints_abrupt_ramp_and_end():
    steps, lv, ends, present = fault_breakpoints([10, -1], [2.0, 1.0])
    assert steps.tolist() == [10] and lv.tolist() == ends.tolist() == [[2.0, 0.0]]
    assert present.tolist() == [[True, False]]
    S, L = RAMP_SEGMENTS, 2 * RAMP_SEGMENTS + 1  # a ramp of L steps
    steps, lv, ends, present = fault_breakpoints([100, -1], [2.0, 1.0], ramp=[L, 0])
    assert len(steps) == S + 1 and steps[0] == 100 and steps[-1] == 100 + L
    assert present[:, 0].all() and not present[:, 1].any()
    # the knots lie on the ramp, each segment ends where the next begins
    np.testing.assert_allclose(lv[:, 0], 2.0 * (steps - 100) / L, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(ends[:-1, 0], lv[1:, 0])
    assert lv[0, 0] == 0.0 and lv[-1, 0] == ends[-1, 0] == 2.0
    # linear interpolation over each segment is the linear ramp at every step
    for k in range(100, 100 + L):
        e = np.searchsorted(steps, k, side="right") - 1
        w = (k - steps[e]) / (steps[e + 1] - steps[e])
        assert lv[e, 0] + w * (ends[e, 0] - lv[e, 0]) == pytest.approx(
            2.0 * (k - 100) / L, abs=1e-14
        )
    # an end inside the ramp cuts it and returns the fault to nominal
    steps, lv, ends, present = fault_breakpoints([100], [1.0], ramp=[64], end=[120])
    assert steps[-1] == 120 and lv[-1, 0] == 0.0 and not present[-1, 0] and np.all(steps <= 120)
    assert ends[-2, 0] == pytest.approx(20 / 64)  # the ramp's value when it ends
    # a ramp shorter than the segment count: one segment per step
    steps, *_ = fault_breakpoints([5], [1.0], ramp=[3])
    assert steps.tolist() == [5, 6, 7, 8]


def test_plan_phases_codes_follow_presence():
    table = fault_table(("p", "q"), np.array([1.0, 0.0]), {"a": {"p": 2.0}, "b": {"q": 1.0}})
    th, codes, steps, present, levels, th_end = plan_phases(
        table, np.array([10, 20]), np.array([1.0, 0.5]), 6, end=np.array([30, -1])
    )
    assert steps.tolist()[:3] == [10, 20, 30]
    assert codes.tolist() == [0, 1, 3, 2, 2, 2]
    assert th[3, 0] == 1.0 and th[3, 1] == pytest.approx(0.5)
    np.testing.assert_array_equal(th_end, th)  # abrupt events: nothing to interpolate
    # a ramp: present (code) from its onset, at nominal there, its end towards the next knot
    th, codes, steps, _, _, th_end = plan_phases(
        table, np.array([10, -1]), np.array([1.0, 1.0]), 4, ramp=np.array([2, 0])
    )
    assert steps.tolist()[:2] == [10, 11] and codes.tolist()[:3] == [0, 1, 1]
    assert th[1, 0] == 1.0 and th_end[1, 0] == pytest.approx(1.5) and th[2, 0] == th_end[1, 0]


@pytest.mark.parametrize("n", [5, 16, 17, 514, 1000])
def test_phase_index_counts_the_events_started_whatever_their_number(n):
    """The truth's phase lookup (a count up to 16 event steps, a binary search above)
    equals the count of event steps ``<= k``, padding phases (NEVER) included."""
    import jax.numpy as jnp

    from uimm_jax.engine.truth import NEVER, TruthPlan, phase_index

    rng = np.random.default_rng(n)
    es = np.sort(rng.integers(0, 5000, (8, n)), axis=1).astype(np.int32)
    es[:, -min(3, n - 1) :] = NEVER
    plan = TruthPlan(None, jnp.asarray(es), None, None, None)
    for k in (0, 1, 100, 2500, 4999, 6000, int(es.min()), int(es[0, 0]), int(es[-1, n // 2])):
        got = np.asarray(phase_index(plan, jnp.int32(k)))
        np.testing.assert_array_equal(got, np.sum(k >= es, axis=1), err_msg=f"k={k}")


def test_a_slow_ramps_truth_follows_the_ramp_not_a_staircase():
    """Air in oil x3 growing over 6 s (256 segments of 234 samples), its first 0.25 s: the
    interpolated truth's states stay within 0.15 measurement sd of the truth with one
    segment per 8 samples, while the same knots held as a staircase (no interpolation)
    are more than 5 sd off."""
    import jax

    from uimm_jax.engine.scan import truth_scan
    from uimm_jax.engine.truth import InputSignal, truth_plan
    from uimm_jax.studies.run import setup_scenario

    jax.config.update("jax_enable_x64", True)
    setup = setup_scenario(parse_scenario(short_dict(sim=2, duration=0.3, events=(0.05, 0.1))))
    sc, dyn = setup.scenario, setup.diagnoser.dyn
    R = np.asarray(sc.measurement_noise)
    states = {}
    for name, segments in (("interpolated", RAMP_SEGMENTS), ("fine", 7500), ("stairs", 0)):
        plan = truth_plan(
            dyn, setup.table, np.array([-1, -1, 200]), np.array([1.0, 1.0, 3.0]),
            np.zeros((3, 3)), R, ramp=np.array([0, 0, 60000]), segments=segments or RAMP_SEGMENTS,
        )  # fmt: skip
        assert plan.cache_end is not None
        if not segments:
            plan = plan._replace(cache_end=None)
        ks = jax.numpy.arange(2700, dtype=jax.numpy.int32)
        signal = InputSignal.from_spec(sc.input)
        zero = np.zeros(2, np.uint32)
        _, (_u, x, _y, _c) = truth_scan(dyn, sc.dt, 1, plan, signal, zero, jax.numpy.zeros(3), ks)
        states[name] = np.asarray(x)
    sd = np.sqrt(np.diag(R))
    off = {k: np.max(np.abs(v - states["fine"]), axis=0) / sd for k, v in states.items()}
    assert off["interpolated"].max() < 0.15, off  # measured 0.09 (p_h)
    assert off["stairs"].max() > 5.0, off  # measured 19


def test_true_magnitudes_are_the_linear_ramps_and_ends_at_every_step():
    """The figures' and exports' truth (``studies.truth.true_magnitudes``) against the
    ramps written out by hand: linear from the onset, constant after, 0 after an end."""
    from uimm_jax.studies.truth import true_magnitudes

    d = short_dict(sim=2, duration=0.5, events=(0.1, 0.2))
    d["events"][0].update(magnitude=2.0, ramp=0.15)  # valve wear, 1500 samples
    d["events"][1].update(magnitude=0.5, ramp=0.01, end=0.4)  # air in oil, 100 samples
    sc = parse_scenario(d)
    names = [n for n in sc.faults]
    got = true_magnitudes(sc, names, 5000)
    k = np.arange(5000)
    vw = 2.0 * np.clip((k - 1000) / 1500, 0, 1) * (k >= 1000)
    aio = 0.5 * np.clip((k - 2000) / 100, 0, 1) * ((k >= 2000) & (k < 4000))
    np.testing.assert_allclose(got[:, names.index("valve_wear")], vw, rtol=0, atol=1e-14)
    np.testing.assert_allclose(got[:, names.index("air_in_oil")], aio, rtol=0, atol=1e-14)
    assert not got[:, names.index("leakage")].any()


def test_events_take_ramp_and_end():
    d = short_dict(duration=1.0, events=(0.2, 0.4))
    d["events"][0]["ramp"] = 0.1
    d["events"][1]["end"] = 0.8
    sc = parse_scenario(d)
    assert sc.events[0].ramp == 0.1 and sc.events[1].end == 0.8
    for key, value, msg in (
        ("ramp", -1.0, r"\[\[events\]\]\[0\]\.ramp"),
        ("end", 0.1, r"\[\[events\]\]\[0\]\.end"),
        ("end", 5.0, r"\[\[events\]\]\[0\]\.end"),
    ):
        bad = short_dict(duration=1.0, events=(0.2, 0.4))
        bad["events"][0][key] = value
        with pytest.raises(Exception, match=msg):
            parse_scenario(bad)


def _case(duration):
    ev = {"fault": "leakage", "time": 0.2, "duration": duration}
    return [{"name": "i", "events": [ev]}]


def test_sweep_ramps_axis_and_durations():
    sc = parse_scenario(short_dict(duration=1.0, events=(0.2, 0.4)))
    spec = sweep_spec(
        sc,
        runs=2,
        ramps=[0.0, 0.1],
        cases=_case([0.1, 0.2]),
    )
    assert spec.ramps == (0.0, 0.1) and spec.cases[0].events[0].duration == (0.1, 0.2)
    with pytest.raises(Exception, match=r"ramps\[0\]: must be in \[0\.0, inf\)"):
        sweep_spec(sc, runs=2, ramps=[-1.0])
    with pytest.raises(Exception, match=r"\.duration"):
        sweep_spec(
            sc,
            runs=2,
            cases=_case([0.3, 0.1]),
        )


# --------------------------------------------------------------------------------------
# The size-estimating diagnoser
# --------------------------------------------------------------------------------------


def _est_setup(sim=2, mag=2.0, duration=0.6, events=(0.2, 0.4), **event_fields):
    from uimm_jax.studies.run import setup_scenario

    d = short_dict(sim, duration=duration, events=events)
    d["filter"].pop("initial_mode_probs")  # written for "uimm": the default for "uimm-est"
    for e in d["events"]:
        e["magnitude"] = mag
        e.update(event_fields)
    return setup_scenario(parse_scenario(d), "uimm-est")


def test_augmented_jacobian_matches_autodiff_of_the_exact_dynamics():
    import jax
    import jax.numpy as jnp

    from uimm_jax.engine.bank import thetas_for_magnitudes

    st = _est_setup()
    diag = st.diagnoser
    aug, table, n, F = diag.aug, diag.table, 3, 3
    declared = jnp.array([True, False, False])
    sets = diag.model_sets(declared)  # (F, M)
    a0 = jnp.full((F, 4), 0.8)
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(n, 4)) * 1e-3)
    u = jnp.full((1, 4), 0.01)
    xa = jnp.concatenate([x, a0 + 0.01], axis=0)

    @jax.jit  # one compile (op by op, the expm's many small kernels compile one by one)
    def bank(xa):
        cache = aug.prepare(sets, a0)
        _, Fa = aug.predict(cache, jnp.concatenate([x, a0], axis=0), u)  # [Fx, Fa] at a0
        xp, _ = aug.predict(cache, xa, u)  # 0.01 away: the first-order expansion
        return Fa, xp

    Fa, xp = bank(xa)

    @jax.jit
    def exact(xa_m, set_m):  # one model, discretised at its own magnitudes
        th = thetas_for_magnitudes(table, set_m[:, None], xa_m[n:, None])
        c = diag.dyn.prepare(th)
        x_next, _ = diag.dyn.predict(c, xa_m[:n, None], u[:, :1])
        return jnp.concatenate([x_next[:, 0], xa_m[n:]])

    jac = jax.jit(jax.jacfwd(exact))
    for m in range(4):
        J = jac(jnp.concatenate([x, a0], axis=0)[:, m], sets[:, m])
        use = np.concatenate([np.ones(n, bool), np.asarray(sets[:, m])])
        np.testing.assert_allclose(
            np.asarray(Fa[:, :, m])[:, use], np.asarray(J)[:n, use], rtol=1e-9, atol=1e-18
        )
        # first-order expansion 0.01 from the reference: the mean is close to exact
        np.testing.assert_allclose(
            np.asarray(xp[:, m]), np.asarray(exact(xa[:, m], sets[:, m])), rtol=1e-3, atol=1e-12
        )


def test_tangent_order_keeps_the_cache_and_nearly_the_derivatives():
    # settings.tangent_order: derivatives through a lower-degree zero-order hold; the cache
    # itself is the full one, bit for bit, and degree 6 is within rounding at |a| <= 3.
    import jax
    import jax.numpy as jnp

    from uimm_jax.engine.uimm_est import EstSettings, build_diagnoser

    diag = _est_setup().diagnoser
    sets = diag.model_sets(jnp.array([True, False, True]))
    a0 = jnp.asarray(np.random.default_rng(1).uniform(0.05, 3.0, (3, 4)))
    prep = jax.jit(diag.aug.prepare, static_argnums=2)
    full = prep(sets, a0, 0)
    for order, tol in ((6, 1e-12), (2, None)):
        cheap = prep(sets, a0, order)
        for a, b in zip(jax.tree.leaves(cheap.base), jax.tree.leaves(full.base), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        err = max(
            float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(np.asarray(b))))
            for a, b in zip(jax.tree.leaves(cheap.jac), jax.tree.leaves(full.jac), strict=True)
        )
        assert err < tol if tol else err > 1e-6, (order, err)  # degree 2 is visibly off
    with pytest.raises(ValueError, match="settings.tangent_order"):
        build_diagnoser("uimm-est", diag.dyn, diag.table, settings=EstSettings(tangent_order=13))


def test_augmented_structured_algebra_equals_the_full_products():
    # predict_cov uses F = [[G], [0, I]] and observe a constant H = [C, 0]: the results must
    # be those of the dense (n + F) x (n + F) algebra, entry for entry.
    import jax
    import jax.numpy as jnp

    from uimm_jax.engine import _block as bk
    from uimm_jax.engine.kalman import kf_predict_cov, kf_update

    st = _est_setup()
    aug, n, F = st.diagnoser.aug, 3, 3
    N = n + F
    rng = np.random.default_rng(1)
    L = rng.standard_normal((N, N, 4))
    P = np.einsum("ikb,jkb->ijb", L, L) + 0.1 * np.eye(N)[..., None]
    G = rng.standard_normal((n, N, 4))
    Q = np.diag(rng.uniform(0.1, 1.0, N))
    full = np.concatenate([G, np.broadcast_to(np.eye(N)[n:, :, None], (F, N, 4))], 0)
    args = (jnp.asarray(P), jnp.asarray(Q)[..., None])  # compiled: op by op is ~180 compiles
    got = np.asarray(jax.jit(aug.predict_cov)(jnp.asarray(G), *args))
    want = np.asarray(jax.jit(kf_predict_cov)(jnp.asarray(full), *args))
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=0)
    np.testing.assert_array_equal(got, np.swapaxes(got, 0, 1))
    cache = st.diagnoser.prepare(jnp.zeros(F, bool), jnp.float64)  # magnitudes at 1
    yp, H = aug.observe(cache, jnp.asarray(rng.standard_normal((N, 4))))
    assert isinstance(H, np.ndarray) and bk.selection(H) == (0, 1, 2)  # [I 0], no tracing
    x = jnp.asarray(rng.standard_normal((N, 4)))
    y = jnp.asarray(rng.standard_normal((3, 1)))
    R = jnp.asarray(np.diag([0.5, 1.0, 2.0]))[..., None]
    sliced = jax.jit(lambda *a: kf_update(*a[:4], H, *a[4:]))(x, jnp.asarray(P), y, yp, R, 1e-150)
    dense = jax.jit(kf_update)(x, jnp.asarray(P), y, yp, jnp.asarray(H), R, 1e-150)  # products
    for a, b in zip(sliced[:5], dense[:5], strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-300)


def test_uimm_est_declares_and_sizes_a_fault_off_the_library_value():
    from uimm_jax.studies.run import execute_run, filter_measurements

    st = _est_setup(sim=1, mag=2.0)  # valve wear at 0.2 s, leakage at 0.4 s, both x2
    res = execute_run(st, filter_measurements, seed=1)
    decl = res.summary["declarations"]
    assert [d["fault"] for d in decl] == ["valve_wear", "leakage"]
    assert all(d["correct"] for d in decl)
    est = res.outputs["magnitude"][-1]
    names = list(st.table.names)
    for f in ("valve_wear", "leakage"):
        assert est[names.index(f)] == pytest.approx(2.0, rel=0.05)
    # the fixed-size UIMM on the same data declares a wrong fault (the issue's failure)
    from uimm_jax.studies.run import setup_scenario

    fixed = execute_run(setup_scenario(st.scenario, "uimm"), filter_measurements, seed=1)
    assert (
        fixed.summary["false_declarations"] > 0
        or fixed.summary["detection_delay_s"]["leakage"] is None
    )


def test_uimm_est_retracts_a_fault_that_ends():
    from uimm_jax.studies.run import execute_run, filter_measurements, setup_scenario

    d = short_dict(2, duration=0.8, events=(0.2, 0.7))
    d["filter"].pop("initial_mode_probs")
    d["events"] = [{"time": 0.2, "fault": "air_in_oil", "magnitude": 1.0, "end": 0.45}]
    st = setup_scenario(parse_scenario(d), "uimm-est")
    res = execute_run(st, filter_measurements, seed=2)
    codes = res.outputs["declared"]
    j = list(st.table.names).index("air_in_oil")
    on = np.flatnonzero(codes & (1 << j))
    assert on.size and 2000 <= on[0] < 2200  # declared within 20 ms of the onset
    assert on[-1] >= 4500 and codes[-1] == 0  # retracted after the end, nothing else left


def test_uimm_est_reopens_a_declared_magnitude_air_in_oil_x3():
    # Air in oil at 3 (Eh / 1000) after valve wear.  Without re-opening the new fault's
    # variance at its declaration, the estimate declared near 1.5 with a variance counted at
    # Eh's larger values creeps towards 3, and the bank retracts valve wear instead
    # (docs/faults.md, "Sizes").
    import dataclasses

    from uimm_jax.engine.uimm_est import Z95
    from uimm_jax.studies.run import execute_run, filter_measurements

    st = _est_setup(sim=2, mag=3.0, duration=0.8, events=(0.2, 0.4))
    j = list(st.table.names).index("air_in_oil")
    diag = st.diagnoser
    # with session 7's other defaults: session 8's (race_below, walk_rel) and session
    # 25's (end_prior) each happen to rescue this run without the re-opening
    no_reopen = diag.settings._replace(reopen_rel=0.0, race_below=0.0, walk_rel=0.0, end_prior=0.0)
    old = dataclasses.replace(st, diagnoser=dataclasses.replace(diag, settings=no_reopen))
    res, res_old = (execute_run(s, filter_measurements, seed=0) for s in (st, old))
    decl = res.summary["declarations"]
    assert [d["fault"] for d in decl] == ["valve_wear", "air_in_oil"]
    assert all(d["correct"] for d in decl) and not res.summary["retractions"]
    est, sd = res.outputs["magnitude"][-1, j], res.outputs["magnitude_sd"][-1, j]
    assert est == pytest.approx(3.0, rel=0.05) and abs(est - 3.0) <= Z95 * sd
    est0, sd0 = res_old.outputs["magnitude"][-1, j], res_old.outputs["magnitude_sd"][-1, j]
    assert res_old.summary["retractions"] or abs(est0 - 3.0) > Z95 * sd0


def _diag_with(diag, **changes):
    """The uimm-est diagnoser ``diag`` with some of its settings changed."""
    import dataclasses

    return dataclasses.replace(diag, settings=diag.settings._replace(**changes))


@pytest.mark.parametrize(
    ("mag", "off"),
    [(0.5, {"race_below": 0.0, "race_floor": 0.0}), (3.0, {"walk_rel": 0.0})],
    ids=["race_below", "walk_rel"],
)
def test_uimm_est_isolates_incipient_valve_wear(mag, off):
    """A 1 s valve-wear ramp (sim 1) is valve wear, never leakage (docs/faults.md, "Ramps").

    Valve wear and leakage both raise ``Kc + Cl``.  Without ``race_below`` and
    ``race_floor`` (either one alone keeps this run right) the hypothesis that falls
    behind while the wear is tiny restarts from the prior at every step and cannot come
    back (at 0.5: leakage declared in 16 of 16 sweep runs); without
    ``walk_rel`` a declared wear growing to 3 is followed with a lag that a small leakage
    explains (16 of 16).  Each run here (seed 0) fails without its setting.
    """
    from uimm_jax.studies.run import execute_run, filter_measurements, setup_scenario

    d = short_dict(1, duration=1.8, events=(0.5, 1.7))
    d["filter"].pop("initial_mode_probs")
    d["events"] = [{"time": 0.5, "fault": "valve_wear", "magnitude": mag, "ramp": 1.0}]
    st = setup_scenario(parse_scenario(d), "uimm-est")
    st_off = with_est_settings(st, st.diagnoser.settings._replace(**off))
    res, res_off = (execute_run(s, filter_measurements, seed=0) for s in (st, st_off))
    assert [(x["fault"], x["correct"]) for x in res.summary["declarations"]] == [
        ("valve_wear", True)
    ]
    j = list(st.table.names).index("valve_wear")
    assert res.outputs["magnitude"][-1][j] == pytest.approx(mag, rel=0.05)
    assert res_off.summary["false_declarations"] > 0


def _race_state(diag, lead_slot, lead_mean):
    """Two runs, nothing declared: run 0 led by ``lead_slot`` at ``lead_mean``, run 1 by
    model 0; valve wear's hypothesis (slot 1) is improbable (1e-5) at 0.3 +- 0.1."""
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    n, F, M, R = 3, 3, 4, 2
    mean = np.zeros((n + F, M, R))
    mean[n:] = 0.5
    mean[n, 1] = 0.3  # valve wear's own estimate
    mean[n + lead_slot - 1, lead_slot, 0] = lead_mean
    cov = np.broadcast_to(np.eye(n + F)[..., None, None] * 0.01, (n + F, n + F, M, R)).copy()
    lp = np.full((M, R), np.log(1e-5))
    lp[lead_slot, 0] = lp[0, 1] = 0.0
    declared = jnp.zeros((F, R), bool)
    st = IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(lp))
    return st, diag.model_sets(declared), declared, jnp.full((F, R), 5, jnp.int32)


@pytest.mark.parametrize(("lead_mean", "kept"), [(0.1, True), (0.5, False)])
def test_race_below_keeps_a_losing_lookalike_filtering(lead_mean, kept):
    # While leakage leads below race_below (a race too small to declare), improbable valve
    # wear keeps its own estimate; led by a larger leakage, or by model 0, or with the
    # setting off, it restarts from the prior.
    st = _est_setup(sim=1)
    diag = st.diagnoser
    s = diag.settings
    assert s.race_below == s.declare_min
    state = _race_state(diag, 2, lead_mean)
    for d2, want in ((diag, kept), (_diag_with(diag, race_below=0.0), False)):
        imm, _ = rules.reset_unused(d2.settings, d2.dyn.n, *state)
        own = np.asarray(imm.mean[3, 1])  # valve wear's own magnitude, per run
        var = np.asarray(imm.cov[3, 3, 1])
        np.testing.assert_allclose(own[0], 0.3 if want else s.prior_mean)
        np.testing.assert_allclose(var[0], 0.01 if want else s.prior_sd**2)
        np.testing.assert_allclose([own[1], var[1]], [s.prior_mean, s.prior_sd**2])


@pytest.mark.parametrize(("lead_mean", "kept"), [(0.2, True), (0.5, False)])
def test_race_floor_keeps_a_lookalike_at_its_floor_filtering(lead_mean, kept):
    # Valve wear's hypothesis sits at its floor (probability 0.1, not improbable).  While
    # leakage leads below race_floor it keeps its own estimate at the floor; led by a
    # larger leakage, or by model 0, or with the setting off, it restarts from the prior,
    # as every hypothesis held at its floor does.  Nothing is declared here, so the rule
    # in every phase (the default since session 11) and race_floor_first act alike.
    st = _est_setup(sim=1)
    diag = st.diagnoser
    s = diag.settings
    assert (s.race_floor, s.race_floor_first) == (0.3, False)  # the defaults
    imm0, sets, declared, since = _race_state(diag, 2, lead_mean)
    mean = imm0.mean.at[3, 1].set(s.floor_mean)  # valve wear's own estimate at the floor
    lp = imm0.log_mode_probs.at[1].set(np.log(0.1))
    state = (imm0._replace(mean=mean, log_mode_probs=lp), sets, declared, since)
    first = _diag_with(diag, race_floor_first=True)
    off = _diag_with(diag, race_floor=0.0)
    for d2, want in ((diag, kept), (first, kept), (off, False)):
        imm, _ = rules.reset_unused(d2.settings, d2.dyn.n, *state)
        own = np.asarray(imm.mean[3, 1])  # valve wear's own magnitude, per run
        var = np.asarray(imm.cov[3, 3, 1])
        np.testing.assert_allclose(own[0], s.floor_mean if want else s.prior_mean)
        np.testing.assert_allclose(var[0], 0.01 if want else s.prior_sd**2)
        np.testing.assert_allclose([own[1], var[1]], [s.prior_mean, s.prior_sd**2])


def test_walk_rel_single_grows_a_lone_declared_faults_walk_only():
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    st = _est_setup(sim=1)
    diag = st.diagnoser
    s = diag.settings
    n, F, M = 3, 3, 4
    mean = np.zeros((n + F, M, 2))
    mean[n : n + 2, 0] = 2.0  # model 0: valve wear and leakage at 2
    cov = np.broadcast_to(np.eye(n + F)[..., None, None] * 0.01, (n + F, n + F, M, 2)).copy()
    state = IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.zeros((M, 2)))
    declared = jnp.asarray([[True, True], [False, True], [False, False]])  # run 1: both
    extra = (s.walk_rel * 2.0) ** 2 - s.walk**2
    assert s.walk_rel_single and extra > 0
    for single in (True, False):  # walk_rel_newest (on by default) is test_second_fault's
        d2 = _diag_with(diag, walk_rel_single=single, walk_rel_newest=False)
        since = jnp.ones(declared.shape, jnp.int32)
        got = np.asarray(rules.walk_rel(d2.settings, d2.dyn.n, state, declared, since).cov) - cov
        want = np.zeros_like(cov)
        for j, r in [(0, 0)] + ([] if single else [(0, 1), (1, 1)]):
            want[n + j, n + j, :, r] = extra  # every model's copy
        np.testing.assert_allclose(got, want, atol=1e-18)


def test_sweep_reports_sizes_and_retractions_of_uimm_est():
    from uimm_jax.studies.sweep import run_sweep

    sc = parse_scenario(short_dict(2, duration=0.5, events=(0.1, 0.3)))
    case = {
        "name": "intermittent",
        "events": [{"fault": "air_in_oil", "time": [0.1, 0.15], "duration": [0.1, 0.2]}],
    }
    steady = {"name": "steady", "events": [{"fault": "air_in_oil", "time": 0.1}]}
    grow = {"fault": "air_in_oil", "time": 0.1, "ramp": 0.1, "growth": "exponential"}
    growing = {"name": "growing", "events": [grow]}
    cases = [case, steady, growing]
    res = run_sweep(sc, runs=16, methods=["uimm-est"], magnitudes=[2.0], cases=cases)
    est = res.estimates
    by_case = {c.case: c.index for c in res.cells}
    i = by_case["intermittent"]
    end = res.end_step[i][:, 2]
    assert np.all((end > res.onset_step[i][:, 2]) & (end - res.onset_step[i][:, 2] <= 2000))
    s = res.summaries[i]
    ok = est["retract_step"][i][:, 2] >= end
    assert s["retraction_probability"]["air_in_oil"] == pytest.approx(ok.mean())
    assert s["retraction_probability"]["air_in_oil"] >= 0.9
    st = res.summaries[by_case["steady"]]
    assert st["magnitude_mare"]["air_in_oil"] < 0.05
    assert 0.0 <= st["magnitude_coverage"]["air_in_oil"] <= 1.0
    assert res.summaries[by_case["fault-free"]]["false_declarations_all"] == 0
    # a growth still under way at the run's end: scored against the truth's level there
    g = by_case["growing"]
    level = 2.0 * (1 - np.exp(-3999 / 1000)) / (1 - 1e-6)  # the last step, 4 tau in
    np.testing.assert_allclose(res.true_magnitude[g][:, 2], level, rtol=1e-12)
    np.testing.assert_array_equal(res.true_magnitude[by_case["steady"]][:, 2], 2.0)
    err = np.abs(est["magnitude"][g][:, 2] / level - 1)
    kept = (res.decl_step[g][:, 2] >= 0) & (est["retract_step"][g][:, 2] < 0)
    assert res.summaries[g]["magnitude_mare"]["air_in_oil"] == pytest.approx(np.median(err[kept]))
    assert kept.mean() >= 0.9  # sized in docs/faults.md, "Exponential growth"
    # runs.csv carries each run's last retraction and end-of-run size (exports.run_rows)
    from uimm_jax.studies.exports import run_rows

    head, rows = run_rows(res)
    for row in rows:
        c, r = row[0], row[5]
        got = dict(zip(head, row, strict=True))
        ret = est["retract_step"][c][r, 2]
        assert (got["air_in_oil:retracted_s"] == "") == (ret < 0)
        if ret >= 0:
            assert round(got["air_in_oil:retracted_s"] / res.dt) == ret + 1
        assert got["air_in_oil:magnitude"] == est["magnitude"][c][r, 2]
        assert got["air_in_oil:magnitude_sd"] == est["magnitude_sd"][c][r, 2]
    assert sum(dict(zip(head, w, strict=True))["air_in_oil:retracted_s"] != "" for w in rows) >= 14


def test_user_plant_sensor_biases_step_ramp_and_end_are_sized_and_recognised():
    """The issue's user-plant line: additive sensor-bias faults, a step, a ramp, an end."""
    import uimm_jax

    d = biased_sensors_dict()  # dt = 1e-3 s; the plant is registered
    res = uimm_jax.run_scenario(parse_scenario(d), seed=3)
    s = res.summary
    assert s["false_declarations"] == 0
    assert [d["fault"] for d in s["declarations"]] == ["bias0", "bias1", "bias2"]
    truth = {"bias0": 1.5, "bias1": 0.7, "bias2": 1.2}
    for d_ in s["declarations"]:  # at the end of the run (bias2: before its retraction)
        assert d_["magnitude"] == pytest.approx(truth[d_["fault"]], rel=0.10)
        lo, hi = d_["magnitude_ci"]
        assert lo < d_["magnitude"] < hi
    assert [(r["fault"], r["correct"]) for r in s["retractions"]] == [("bias2", True)]
    # The settings counted in steps keep their meaning in seconds at this dt (steps_dt):
    # retract_hold's 200 samples at 1e-4 s are 20 samples here (200 before session 12).
    assert s["retractions"][0]["time"] - 1.6 <= 0.03
    assert s["detection_delay_s"]["bias1"] <= 0.06  # a ramp that ends at 50 ms
    assert s["mode_accuracy"] >= 0.98
    # timeseries.npz carries the per-step sizes and sds (exports.TIMESERIES_OPTIONAL_KEYS),
    # whose last declared values are the summary's (bias0 and bias1 stay declared)
    from uimm_jax.studies.exports import timeseries_arrays

    a = timeseries_arrays(res)
    assert a["magnitude"].shape == a["magnitude_sd"].shape == (len(a["time"]), 3)
    for j, d_ in enumerate(s["declarations"][:2]):
        assert d_["magnitude"] == a["magnitude"][-1, j]
        sd = a["magnitude_sd"][-1, j]
        assert d_["magnitude_ci"] == pytest.approx(
            [d_["magnitude"] - 1.96 * sd, d_["magnitude"] + 1.96 * sd], rel=1e-4
        )


def test_gathered_cache_rebuild_equals_the_whole_batch_rebuild():
    # Runs that need a rebuild are gathered into a group and pull their own result back;
    # every run must get exactly the numbers of the whole-batch rebuild (the per-run rule).
    import jax
    import jax.numpy as jnp

    import uimm_jax.engine._est_rebuild as ue

    diag = _est_setup().diagnoser
    F, M, runs = 3, 4, (5, 8)  # two run axes, 40 runs
    rng = np.random.default_rng(2)
    declared = jnp.asarray(rng.random((F,) + runs) < 0.4)
    a0 = jnp.asarray(rng.uniform(0.2, 3.0, (F, M) + runs))
    old = diag.prepare(jnp.zeros((F,) + runs, bool), jnp.float64)  # compiled, not op by op
    whole = jax.jit(lambda need, d, a: jax.tree.map(ue.per_run(need), diag._cache(d, a), old))
    got = jax.jit(
        lambda need, d, a, g: ue.gathered(diag._cache, need, (d, a), old, g), static_argnums=3
    )
    for count, group in ((3, 8), (8, 8), (12, 32), (32, 32)):  # one compile per group
        need = np.zeros(40, bool)
        need[rng.choice(40, count, replace=False)] = True
        need = jnp.asarray(need.reshape(runs))
        for a, b in zip(
            jax.tree.leaves(got(need, declared, a0, group)),
            jax.tree.leaves(whole(need, declared, a0)),
            strict=True,
        ):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow
def test_uimm_est_batch_steps_are_the_same_with_and_without_gathering(monkeypatch):
    # The whole step over a batch of 40 runs, with the gathered rebuilds (groups of 8 and
    # 32, the whole batch above) and with the whole-batch rebuild only: bit for bit.
    import jax
    import jax.numpy as jnp

    import uimm_jax.engine._est_rebuild as ue
    from uimm_jax.studies.run import simulate_scenario

    st = _est_setup(duration=0.05, events=(0.01, 0.03), mag=0.5)
    diag, params = st.diagnoser, st.params
    B, N = 40, 500
    truth = simulate_scenario(st, 0)
    rng = np.random.default_rng(3)
    sd = np.sqrt(np.diag(np.asarray(params.imm.R)))[None, :, None]
    ys = jnp.asarray(truth["y"][:N, :, None] + sd * rng.standard_normal((N, 3, B)))  # runs differ
    us = jnp.asarray(np.broadcast_to(truth["u"][:N, :, None], (N, truth["u"].shape[1], B)))
    s0 = jax.tree.map(lambda a: jnp.broadcast_to(a[..., None], a.shape + (B,)), st.init_state)

    def run():
        def body(s, uy):
            s2, info = diag.step(s, params, *uy, with_cov=False)
            return s2, (info, jnp.sum(jnp.any(s2.cache.a0 != s.cache.a0, axis=(0, 1))))

        return jax.jit(lambda s: jax.lax.scan(body, s, (us, ys)))(s0)

    gathered = run()
    monkeypatch.setattr(ue, "REBUILD_GROUPS", ())
    plain = run()
    counts = np.asarray(gathered[1][1])
    assert np.any((counts > 0) & (counts <= 8)) and np.any((counts > 8) & (counts <= 32))
    assert np.any(counts > 32)  # every tier was taken
    for a, b in zip(jax.tree.leaves(gathered), jax.tree.leaves(plain), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
