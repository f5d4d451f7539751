"""A declared fault's magnitude rate in the size-estimating UIMM (``rate_steps``, ``rate_auto``).

A fault that grows (a ramp, a wear) is followed by a random walk only with a lag, unless
the walk is large; a large walk lets a declared estimate wander and absorb a new fault
(docs/faults.md, "Ramps").  The constant-velocity model of a magnitude,
``a[k+1] = a[k] + r[k]``, ``r[k+1] = r[k] + w``, follows a ramp without lag with a small
walk.  Here the rate ``r`` of each declared fault is carried per run outside the bank's
covariance (the state ``[x; a]`` keeps its size): before a step every model's estimate of
the fault moves by ``r`` (:func:`drift`), and after it ``r`` takes a share of model 0's
correction of the estimate (:func:`rate_gain`), the alpha-beta form of that model's
Kalman filter.  With ``rate_walk`` the rate instead only measures the estimate's average
drift, and evidence of growth widens the declared fault's walk (:func:`growth_walk`).
Off by default (docs/design.md section 5 and docs/faults.md, "Session 10: a magnitude
rate", say what each form did).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from uimm_jax.engine.uimm_est_types import EstSettings

__all__ = ["drift", "growth_walk", "rate_gain", "rate_on", "rate_update"]


def drift(s: EstSettings, st, n: int, declared: jax.Array, rate: jax.Array):
    """Every model's estimate of a declared fault moved by its rate (``rate_steps``).

    The prediction of the constant-velocity model ``a[k+1] = a[k] + r[k]``; returns the
    state and model 0's predicted magnitudes ``(F, *runs)``, against which the rate is
    corrected after the step.  With ``rate_walk`` the means stay (the rate is then only
    the evidence of growth that widens the walk, in the diagnoser's step).
    """
    if s.rate_walk:
        return st, st.mean[n:, 0]
    mean = st.mean.at[n:].add(jnp.where(declared, rate, 0.0)[:, None])
    return st._replace(mean=mean), mean[n:, 0]


def rate_on(s: EstSettings) -> bool:
    """Whether declared magnitudes carry a rate (``rate_steps``, ``rate_auto``, ``rate_walk``)."""
    return bool(s.rate_steps or s.rate_auto or s.rate_walk)


def rate_gain(s: EstSettings, var_pred: jax.Array, var_post: jax.Array):
    """The share of model 0's correction of a magnitude that its rate takes.

    ``1 / rate_steps``, or with ``rate_auto`` the steady-state gain pair of the
    constant-velocity model (the alpha-beta filter, ``beta = alpha^2 / (2 - alpha)``,
    Benedict and Bordner) at ``alpha = 1 - var_post / var_pred``, the magnitude's own
    variance reduction in this step: the rate then follows within about ``2 / alpha``
    steps, as fast as the walk lets the magnitude itself follow.
    """
    if not s.rate_auto:
        return 1.0 / s.rate_steps
    alpha = jnp.clip(1.0 - var_post / jnp.maximum(var_pred, 1e-300), 0.0, 1.0)
    return alpha / (2.0 - alpha)


def rate_update(s: EstSettings, rate, var_pred, var_post, correction) -> jax.Array:
    """The rate after a step: ``rate + gain * correction``, kept ``>= 0``, then decayed.

    With ``rate_walk`` (no drift: the correction is the estimate's whole change) it is
    the average ``rate + gain * (correction - rate)`` instead, signed and not decayed.

    ``correction`` is model 0's change of the magnitude by the step (estimate after it
    minus the drifted prediction).  A fault grows from nominal towards its magnitude and
    ends abruptly (the truth's ramps and ``end``; an end is the retraction hypothesis'
    business), so the rate is never negative: a declared fault's estimate cannot run
    down at a learnt rate to absorb a new fault, which it did (docs/faults.md).  With
    ``rate_decay`` steps the rate decays by ``1 - 1 / rate_decay`` per step (a
    first-order Markov rate, Singer's model): it lasts only as long as the corrections
    sustain it, so a weakly observable estimate does not run on after its fault stopped.
    """
    if s.rate_walk:  # the signed average of the estimate's drift (``growth_walk``)
        return rate + rate_gain(s, var_pred, var_post) * (correction - rate)
    rate = jnp.maximum(rate + rate_gain(s, var_pred, var_post) * correction, 0.0)
    return rate * (1.0 - 1.0 / s.rate_decay) if s.rate_decay else rate


GROWTH_Z = 3.0
"""How many of its standard deviations the drift must exceed to widen the walk."""


def growth_walk(s: EstSettings, rate: jax.Array, q: jax.Array) -> jax.Array:
    """``rate_walk``: the variance a declared fault's walk gains from evidence of growth.

    ``rate`` is the estimate's drift per step averaged over about ``rate_steps`` steps
    (not kept ``>= 0``).  For a constant fault the estimate moves by about the walk's
    standard deviation per step, so the average has standard deviation
    ``sqrt(q_w / (2 rate_steps))`` for a walk of variance ``q_w``: only the growth beyond
    ``GROWTH_Z`` of those counts, ``(rate_walk * max(rate - GROWTH_Z sd, 0))^2``, with
    ``q_w`` the walk ``q`` plus that gain (one fixed-point step), so that the walk's own
    noise does not widen it further (docs/faults.md, "Session 10: a magnitude rate").
    """
    n = 2.0 * max(s.rate_steps, 1)
    extra = (s.rate_walk * jnp.maximum(rate - GROWTH_Z * jnp.sqrt(q / n), 0.0)) ** 2
    return (s.rate_walk * jnp.maximum(rate - GROWTH_Z * jnp.sqrt((q + extra) / n), 0.0)) ** 2
