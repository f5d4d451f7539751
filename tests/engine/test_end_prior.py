"""``end_prior``: the prior probability per sample that a declared fault ends, the
transition into its retraction hypothesis (docs/faults.md, "Ramps", "Session 24")."""

from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest

from uimm_jax.engine import _est_rules as rules
from uimm_jax.engine.uimm_est_types import EstSettings

F, M = 3, 4
PATTERNS = np.array(list(itertools.product([False, True], repeat=F))).T  # (F, 8): every set


# -- end_prior: the prior probability that a declared fault ends -----------------------


def _naive_end_prior(log_trans, declared, p):
    runs = declared.shape[1]
    F, M = declared.shape[0], declared.shape[0] + 1  # noqa: N806 (the module's names)
    q = np.repeat(np.exp(log_trans)[..., None], runs, axis=-1)
    for r in range(runs):
        if declared[:, r].sum() < 2:  # a lone declared fault: the filter's prior
            continue
        for j in range(F):
            if declared[j, r]:
                for i in range(M):
                    if i != j + 1:
                        q[i, j + 1, r] = p
        for i in range(M):
            q[i, i, r] = 1.0 - sum(q[i, k, r] for k in range(M) if k != i)
    out = np.log(q)
    for r in range(runs):
        if declared[:, r].sum() < 2:
            out[..., r] = log_trans
    return out


def test_end_prior_sets_every_transition_into_a_retraction_hypothesis():
    import jax.numpy as jnp

    stay = 0.9999
    q = np.full((M, M), (1 - stay) / (M - 1)) + np.eye(M) * (stay - (1 - stay) / (M - 1))
    got = np.asarray(rules.end_prior(jnp.asarray(np.log(q)), jnp.asarray(PATTERNS), 1e-7))
    want = _naive_end_prior(np.log(q), PATTERNS, 1e-7)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    np.testing.assert_allclose(np.exp(got).sum(axis=1), 1.0, rtol=1e-12)
    none = PATTERNS.sum(axis=0) < 2  # fewer than two declared: the filter's, bit for bit
    np.testing.assert_array_equal(got[..., none], np.log(q)[..., None].repeat(none.sum(), -1))
    assert EstSettings().end_prior == 1e-6  # the default since session 25


def test_end_prior_table_gathers_the_direct_result_bit_for_bit():
    """Up to ``END_TABLE_MAX_F`` faults the matrices of every declared set are computed
    once and gathered per run; the result is the per-run computation's, bit for bit,
    and above that count the per-run computation is used (checked on the naive loop)."""
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(3)
    q = rng.random((M, M)) + np.eye(M) * 40.0
    q /= q.sum(axis=1, keepdims=True)
    declared = rng.random((F, 7, 5)) < 0.5  # (F, *runs) with two batch axes
    table = jax.jit(lambda lt, d: rules.end_prior(lt, d, 1e-6))(jnp.log(q), declared)
    direct = jax.jit(lambda lt, d: rules._end_prior(lt, d, 1e-6))(jnp.log(q), declared)
    np.testing.assert_array_equal(np.asarray(table), np.asarray(direct))
    big = rules.END_TABLE_MAX_F + 1  # no table: 2^9 sets
    qb = np.full((big + 1, big + 1), 1e-4) + np.eye(big + 1) * (1 - (big + 1) * 1e-4)
    db = rng.random((big, 6)) < 0.3
    got = np.asarray(rules.end_prior(jnp.log(qb), jnp.asarray(db), 1e-6))
    np.testing.assert_allclose(got, _naive_end_prior(np.log(qb), db, 1e-6), rtol=1e-12)


def test_end_prior_is_a_rate_converted_with_dt_and_checked():
    from uimm_jax.engine.uimm_est_types import END_PRIOR_MAX, est_setting_problem, settings_at_dt

    s = EstSettings(end_prior=1e-6)  # given at steps_dt = 1e-4 s
    assert settings_at_dt(s, 1e-4) is s
    assert settings_at_dt(s, 1e-3).end_prior == pytest.approx(1e-5, rel=1e-12)  # per second
    assert settings_at_dt(EstSettings(end_prior=5e-3), 1e-2).end_prior == END_PRIOR_MAX
    assert est_setting_problem("end_prior", 0.0) is None
    msg = est_setting_problem("end_prior", 0.5)
    assert msg is not None and "[0, 0.01]" in msg


def test_end_prior_gives_no_nan_when_the_ends_would_fill_a_row():
    import jax.numpy as jnp

    q = np.full((M, M), 0.1) + np.eye(M) * 0.6
    got = np.asarray(rules.end_prior(jnp.asarray(np.log(q)), jnp.asarray(PATTERNS), 0.5))
    assert not np.isnan(got).any()


@pytest.mark.slow
def test_end_prior_keeps_valve_wear_after_air_in_oils_ramp_on_a_long_run():
    """Sim 2, valve wear and air in oil each at 2 over 10 s ramps, 11 s after the second
    ramp (seed 4).  On session 25's settings (``drift_walk = 0``), with the filter's own
    prior of an end (``end_prior = 0``, 3.3e-5 per sample) "D - valve wear" takes the lead
    on a small edge of fit and valve wear is retracted about 6 s after the ramp, with air
    in oil's interval below its truth; with ``end_prior = 1e-6`` (the default since
    session 25) valve wear stays declared and both intervals cover 2.  On today's defaults
    (``drift_walk = 3`` since session 28, which alone also keeps valve wear here: session
    30) the same holds."""
    import uimm_jax
    from _robustness_helpers import sim2_ramps
    from uimm_jax.scenario.parse import parse_scenario

    def run(**est):
        d = sim2_ramps(duration=32.5, ramp=10.0, second_at=11.5)
        d["filter"]["est"].update(est)
        return uimm_jax.run_scenario(parse_scenario(d), seed=4).summary

    out = {p: run(end_prior=p, drift_walk=0.0) for p in (0.0, 1e-6)}
    out["defaults"] = run()
    assert [(x["fault"], x["correct"]) for x in out[0.0]["retractions"]] == [("valve_wear", False)]
    lo, hi = out[0.0]["declarations"][1]["magnitude_ci"]
    assert hi < 2.0  # air in oil's interval misses the truth, low
    for key in (1e-6, "defaults"):
        assert out[key]["retractions"] == []
        assert [x["fault"] for x in out[key]["declarations"]] == ["valve_wear", "air_in_oil"]
        for x in out[key]["declarations"]:
            assert x["correct"] and x["magnitude_ci"][0] <= 2.0 <= x["magnitude_ci"][1], x


def test_an_end_prior_converted_to_the_plants_dt_is_warned_about():
    from uimm_jax.engine import uimm_est
    from uimm_jax.engine.uimm_est_types import settings_at_dt
    from uimm_jax.errors import UIMMWarning

    given = EstSettings(end_prior=2e-6)  # not the default: a value the user gave
    used = settings_at_dt(given, 1e-3)
    with pytest.warns(UIMMWarning, match=r"end_prior 2e-06 -> [0-9.]+e-0[56] per sample"):
        uimm_est._warn_converted(given, used)
    default = EstSettings()  # the default end_prior is converted without a warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uimm_est._warn_converted(default, settings_at_dt(default, 1e-3))
