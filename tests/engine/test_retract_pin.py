"""``retract_pin``: a retraction hypothesis holds the other declared faults at model 0's
estimates (docs/faults.md, "Ramps", "Session 20")."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from uimm_jax.engine import _est_rules as rules
from uimm_jax.engine.uimm_est_types import EstSettings

N, F, M = 3, 3, 4
PATTERNS = np.array(list(itertools.product([False, True], repeat=F))).T  # (F, 8): every set


def _naive_pinned(use, declared):
    out = use.copy()
    for r in range(declared.shape[1]):
        for j in range(F):  # slot j + 1 is "D - f_j" when j is declared
            for k in range(F):
                if declared[j, r] and declared[k, r] and k != j:
                    out[k, j + 1, r] = False
    return out


def test_pinned_drops_exactly_the_other_declared_faults_of_each_retraction_hypothesis():
    import jax.numpy as jnp

    rng = np.random.default_rng(0)
    use = rng.random((F, M, PATTERNS.shape[1])) < 0.8
    got = np.asarray(rules.pinned(jnp.asarray(use), jnp.asarray(PATTERNS)))
    np.testing.assert_array_equal(got, _naive_pinned(use, PATTERNS))
    # model 0 and the hypotheses "D + f_j" keep every magnitude they used
    assert np.array_equal(got[:, 0], use[:, 0])
    for j in range(F):
        undeclared = ~PATTERNS[j]
        assert np.array_equal(got[:, j + 1, undeclared], use[:, j + 1, undeclared])


def _random_state(seed, runs):
    import jax.numpy as jnp

    from uimm_jax.engine.imm import IMMState

    rng = np.random.default_rng(seed)
    a = rng.normal(size=(N + F, N + F, M, runs))
    cov = np.einsum("ijmr,kjmr->ikmr", a, a) + 1e-3 * np.eye(N + F)[..., None, None]
    mean = rng.normal(1.0, 0.3, size=(N + F, M, runs))
    logp = np.log(np.full((M, runs), 1.0 / M))
    return IMMState(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(logp))


@pytest.mark.parametrize("seed", [0, 1])
def test_reset_with_pinned_use_hands_model_0s_estimates_to_the_retraction_hypotheses(seed):
    """After the reset, ``D - f_j`` carries model 0's mean and variance of every other
    declared fault, uncorrelated with its state and its other magnitudes; what it keeps
    of its own state, and every other model, is what the reset without the pin gives;
    the covariance stays symmetric positive definite."""
    import jax.numpy as jnp

    declared = jnp.asarray(PATTERNS)
    runs = PATTERNS.shape[1]
    st = _random_state(seed, runs)
    s = EstSettings()
    since = jnp.full((F, runs), 10, jnp.int32)
    use = np.ones((F, M, runs), bool)
    for j in range(F):  # "D - f_j" does not use a_j; "D + f_j" uses it
        use[j, j + 1] = ~PATTERNS[j]
    use = jnp.asarray(use)
    plain, _ = rules.reset_unused(s, N, st, use, declared, since)
    pinned, _ = rules.reset_unused(s, N, st, rules.pinned(use, declared), declared, since)
    mean0, cov0 = np.asarray(st.mean), np.asarray(st.cov)
    pm, pc = np.asarray(pinned.mean), np.asarray(pinned.cov)
    qm, qc = np.asarray(plain.mean), np.asarray(plain.cov)
    touched = np.zeros((N + F, M, runs), bool)
    for r in range(runs):
        for j in range(F):
            for k in range(F):
                if PATTERNS[j, r] and PATTERNS[k, r] and k != j:
                    i, m = N + k, j + 1
                    touched[i, m, r] = True
                    assert pm[i, m, r] == mean0[i, 0, r]
                    assert pc[i, i, m, r] == cov0[i, i, 0, r]
                    others = np.delete(pc[i, :, m, r], i)
                    assert np.all(others == 0.0) and np.all(np.delete(pc[:, i, m, r], i) == 0.0)
    assert touched.any()
    np.testing.assert_array_equal(pm[~touched], qm[~touched])
    keep = ~(touched[:, None] | touched[None])
    np.testing.assert_array_equal(pc[keep], qc[keep])
    sym = np.moveaxis(pc, (0, 1), (-2, -1))
    np.testing.assert_array_equal(sym, np.swapaxes(sym, -1, -2))
    assert np.all(np.linalg.eigvalsh(sym) > 0)


def test_retract_pin_is_read_from_the_scenario_and_off_by_default():
    from _robustness_helpers import short_dict
    from uimm_jax.scenario.parse import parse_scenario

    assert EstSettings().retract_pin is False
    d = short_dict(2, duration=0.2, events=(0.05, 0.1))
    d["filter"]["est"] = {"retract_pin": True}
    assert parse_scenario(d).filter.est.retract_pin is True


# -- retract_after: no retraction by hypothesis right after another declaration ----------


def _naive_after(declared, age, after):
    held = np.zeros_like(declared)
    for r in range(declared.shape[1]):
        for i in range(F):
            others = [k for k in range(F) if k != i and declared[k, r] and age[k, r] < after]
            held[i, r] = declared[i, r] and bool(others)
    return held


def test_after_declaration_holds_every_declared_fault_but_the_newly_declared_alone():
    import jax.numpy as jnp

    rng = np.random.default_rng(1)
    s = EstSettings(retract_after=50)
    declared = np.tile(PATTERNS, 4)
    age = rng.integers(0, 101, size=declared.shape).astype(np.int32)
    got = np.asarray(rules.after_declaration(s, jnp.asarray(declared), jnp.asarray(age)))
    want = _naive_after(declared, age, 50)
    np.testing.assert_array_equal(got, want)
    assert want.any() and (declared & ~want).any()  # both cases are drawn
    lone = declared.sum(axis=0) == 1
    assert not got[:, lone].any()  # a lone declared fault is never held


def test_declaration_age_restarts_at_a_declaration_and_stops_at_retract_after():
    import jax.numpy as jnp

    s = EstSettings(retract_after=3, decl_restart=0)  # the age counts to the larger of the two
    fresh = np.array([[True, False, False, False, False, True, False]])
    age = np.full((1, 1), 3, np.int32)
    seen, want, a = [], [], 3
    for f in fresh[0]:
        age = np.asarray(rules.declaration_age(s, jnp.asarray(age), jnp.asarray([[f]])))
        a = 0 if f else min(a + 1, 3)
        seen.append(int(age[0, 0]))
        want.append(a)
    assert seen == want == [0, 1, 2, 3, 3, 0, 1]


def test_retract_after_keeps_valve_wear_when_air_in_oil_is_declared_mid_ramp():
    """Sim 2's 0.1 s ramps at 2 (seed 0): air in oil is declared mid-ramp and "D - valve
    wear" explains its lag; without the rule valve wear is retracted tens of ms later,
    with ``retract_after = 4000`` (0.4 s) it stays declared and its interval covers 2.
    Run with ``drift_walk = 0`` (the defaults of session 21, which the rule was made on):
    since session 28's ``drift_walk = 3`` valve wear's walk follows its ramp and this run
    keeps it declared without the rule as well."""
    import uimm_jax
    from _robustness_helpers import sim2_ramps
    from uimm_jax.scenario.parse import parse_scenario

    d = sim2_ramps(duration=1.9, ramp=0.1, second_at=1.6)
    d["filter"]["est"]["drift_walk"] = 0.0
    out = {}
    for after in (0, 4000):
        d["filter"]["est"]["retract_after"] = after
        out[after] = uimm_jax.run_scenario(parse_scenario(d), seed=0).summary
    declared = [(x["fault"], x["correct"]) for x in out[4000]["declarations"]]
    assert declared == [("valve_wear", True), ("air_in_oil", True)]
    assert [x["fault"] for x in out[0]["retractions"]] == ["valve_wear"]
    assert out[4000]["retractions"] == []
    lo, hi = out[4000]["declarations"][0]["magnitude_ci"]
    assert lo <= 2.0 <= hi
