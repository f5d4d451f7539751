"""uimm-est's magnitude rate (``rate_steps``, ``rate_auto``, ``rate_decay``; off by default).

The rate's arithmetic is checked on a scalar random-walk Kalman filter of a magnitude
observed directly, the loop it closes inside the bank (docs/faults.md, "Session 10: a
magnitude rate"): with the rate a ramp is followed without the walk's lag.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uimm_jax.engine.uimm_est import EstSettings
from uimm_jax.engine.uimm_est_rate import drift, rate_gain, rate_update


def _track(settings, slope, steps=4000, stop=None, q=1e-8, r=1e-4, seed=0):
    """A scalar walk KF (walk variance ``q``, measurement variance ``r``) of a ramp of
    ``slope`` per step (flat after ``stop``), with the rate of ``settings`` (or none):
    returns the truth minus the estimate and the rate at every step."""
    noise = np.sqrt(r) * np.random.default_rng(seed).standard_normal(steps)
    k = np.arange(steps)
    truth = slope * np.minimum(k, steps if stop is None else stop)
    on = settings is not None

    def step(carry, zt):
        a, p, rate = carry
        z, t = zt
        pred = a + rate if on else a
        p_pred = p + q
        gain = p_pred / (p_pred + r)
        a_new = pred + gain * (z - pred)
        p_new = (1.0 - gain) * p_pred
        if on:
            rate = rate_update(settings, rate, p_pred, p_new, a_new - pred)
        return (a_new, p_new, rate), (t - a_new, rate)

    init = (jnp.float64(0.0), jnp.float64(1e-2), jnp.float64(0.0))
    _, (lag, rates) = jax.lax.scan(step, init, (jnp.asarray(truth + noise), jnp.asarray(truth)))
    return np.asarray(lag), np.asarray(rates)


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def test_a_rate_follows_a_ramp_without_the_walks_lag():
    """The walk alone lags a ramp by about ``slope / alpha``; with the rate (either gain)
    the lag at the end is a small fraction of that, and the rate is the slope."""
    slope = 1e-4
    walk_lag = np.mean(_track(None, slope)[0][-1000:])
    assert walk_lag > 5e-3  # the lag the rate is for (about slope / alpha)
    for s in (EstSettings(rate_auto=True), EstSettings(rate_steps=200)):
        lag, rates = _track(s, slope)
        assert abs(np.mean(lag[-1000:])) < 0.1 * walk_lag
        assert np.mean(rates[-1000:]) == pytest.approx(slope, rel=0.1)


def test_the_rate_never_runs_down_and_decays_without_evidence():
    """A falling magnitude leaves the rate near 0 (the walk's lag, as without a rate).
    Without information (no variance reduction, no correction) the rate stays as it is,
    the runaway of a weakly observable estimate; ``rate_decay`` lets it decay."""
    falling, rates = _track(EstSettings(rate_auto=True), -1e-4)
    assert np.all(rates >= 0.0) and np.mean(rates[-1000:]) < 0.05 * 1e-4
    walk_lag = np.mean(_track(None, -1e-4)[0][-1000:])
    assert np.mean(falling[-1000:]) == pytest.approx(walk_lag, rel=0.1)
    one = jnp.ones(1)
    for decay, factor in ((0, 1.0), (50, (1 - 1 / 50) ** 100)):
        s = EstSettings(rate_auto=True, rate_decay=decay)
        rate = 1e-4 * one
        for _ in range(100):
            rate = rate_update(s, rate, one, one, 0.0 * one)
        assert float(rate[0]) == pytest.approx(1e-4 * factor, rel=1e-9)
    assert factor < 0.14


def test_rate_gain_is_the_alpha_beta_gain_of_the_variance_reduction():
    """``rate_auto``: ``alpha / (2 - alpha)`` at ``alpha = 1 - var_post / var_pred``."""
    s = EstSettings(rate_auto=True)
    var_pred = jnp.asarray([1.0, 1.0, 1.0])
    var_post = jnp.asarray([1.0, 0.5, 0.0])
    np.testing.assert_allclose(rate_gain(s, var_pred, var_post), [0.0, 0.5 / 1.5, 1.0])
    assert rate_gain(EstSettings(rate_steps=4), var_pred, var_post) == 0.25


def test_drift_moves_only_declared_magnitudes_in_every_model():
    """``drift``: every model's magnitude of a declared fault moves by its rate."""
    from uimm_jax.engine.imm import IMMState

    n, F, M = 2, 3, 4
    mean = jnp.arange((n + F) * M, dtype=jnp.float64).reshape(n + F, M)
    st = IMMState(mean, jnp.zeros((n + F, n + F, M)), jnp.zeros(M))
    declared, rate = jnp.asarray([True, False, True]), jnp.asarray([0.5, 7.0, -1.0])
    out, pred0 = drift(EstSettings(rate_auto=True), st, n, declared, rate)
    expect = np.asarray(mean).copy()
    expect[n] += 0.5
    expect[n + 2] -= 1.0
    np.testing.assert_array_equal(out.mean, expect)
    np.testing.assert_array_equal(pred0, expect[n:, 0])
    same, pred0 = drift(EstSettings(rate_steps=9, rate_walk=10.0), st, n, None, None)
    assert same is st and np.array_equal(pred0, mean[n:, 0])  # rate_walk: means stay


def test_rate_settings_are_off_by_default_and_checked():
    """The defaults carry no rate; a negative ``rate_steps`` or ``rate_decay`` is refused."""
    from uimm_jax.engine.uimm_est import build_diagnoser

    s = EstSettings()
    assert (s.rate_steps, s.rate_auto, s.rate_decay, s.rate_walk) == (0, False, 0, 0.0)
    for name in ("rate_steps", "rate_decay", "rate_walk"):
        with pytest.raises(ValueError, match=name):
            build_diagnoser("uimm-est", None, None, settings=EstSettings(**{name: -1}))
    with pytest.raises(ValueError, match="rate_walk: needs rate_steps"):
        build_diagnoser("uimm-est", None, None, settings=EstSettings(rate_walk=10.0))


def test_growth_walk_counts_only_drift_beyond_its_noise():
    """``rate_walk``: no extra walk for a drift within ``GROWTH_Z`` standard deviations of
    a constant fault's average increment (a falling one included); beyond, the walk's
    standard deviation grows as ``rate_walk`` times the excess."""
    from uimm_jax.engine.uimm_est_rate import GROWTH_Z, growth_walk

    s = EstSettings(rate_steps=20000, rate_walk=10.0)
    q = jnp.asarray(9e-8)
    noise_sd = float(jnp.sqrt(q / 40000))
    for rate in (0.0, -1e-3, 0.99 * GROWTH_Z * noise_sd):
        assert float(growth_walk(s, jnp.asarray(rate), q)) == 0.0
    big = 1e-3  # far above the noise of a constant fault's average
    sd = np.sqrt(float(growth_walk(s, jnp.asarray(big), q)))
    # the walk's own noise at that sd raises the threshold: 10 (big - 3 sd / sqrt(40000))
    assert sd == pytest.approx(10.0 * (big - GROWTH_Z * np.sqrt((9e-8 + 1e-4) / 40000)), rel=0.02)


def test_with_rate_walk_the_rate_is_the_average_drift():
    """``rate_walk``: the estimate is not moved, so the rate is the plain average of its
    changes (signed), not their running sum."""
    s = EstSettings(rate_steps=10, rate_walk=5.0)
    one = jnp.ones(1)
    rate = 0.0 * one
    for _ in range(200):
        rate = rate_update(s, rate, one, one, -2e-4 * one)
    assert float(rate[0]) == pytest.approx(-2e-4, rel=1e-6)
