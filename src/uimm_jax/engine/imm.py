"""One cycle of the interacting multiple model (IMM) estimator, paper eqs. (15)-(31).

Layout ("batch-minor"): a bank state has the model axis *last* and any Monte Carlo run
axes just before it -- ``mean`` is ``(n, *runs, M)``, ``cov`` is ``(n, n, *runs, M)``,
``log_mode_probs`` is ``(*runs, M)``.  The public :func:`uimm_jax.imm_filter` converts to
and from the user-facing leading-model-axis layout once, outside the time loop.

Mode probabilities are kept as logarithms and normalised with a max-shifted log-sum-exp;
a model whose predicted probability is exactly zero (an absorbing fault mode, a UIMM
model masked out after a declaration) is handled without ``0/0``: its mixing weights
fall back to its own previous estimate, and its probability stays ``-inf``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from uimm_jax.engine import _block as bk
from uimm_jax.engine.kalman import kf_predict_cov, kf_update

__all__ = ["IMMParams", "IMMState", "StepInfo", "imm_step", "log_normalize", "mix"]

# Up to this many models the mixing covariance (eq. 17) sums per-pair spreads,
# O(n^2 M^2) work and memory per run; larger (combinatorial) banks use the
# second-moment form (see :func:`mix`).
PAIRWISE_MAX_MODELS = 16

# Health flag bits reported per step.
HEALTH_COV_REPAIRED = 1  # an innovation covariance was not numerically PD: pivots floored
HEALTH_NONFINITE = 2  # a non-finite value was caught and replaced
HEALTH_GATED = 4  # the measurement was rejected by the innovation gate
HEALTH_MISSING = 8  # at least one measurement channel was missing (NaN)


class IMMState(NamedTuple):
    """Carried IMM state (batch-minor).

    Attributes:
        mean: ``(n, *runs, M)`` per-model posterior means.
        cov: ``(n, n, *runs, M)`` per-model posterior covariances.
        log_mode_probs: ``(*runs, M)`` log mode probabilities (``-inf`` = impossible).
    """

    mean: jax.Array
    cov: jax.Array
    log_mode_probs: jax.Array


class IMMParams(NamedTuple):
    """Differentiable parameters of an IMM step.

    Attributes:
        log_transition: ``(M, M)`` (or ``(*runs, M, M)``) log of the transition matrix,
            ``log P(mode j at k+1 | mode i at k)``; ``-inf`` marks an impossible switch.
        Q: ``(n, n)`` process noise covariance.
        R: ``(m, m)`` measurement noise covariance.
    """

    log_transition: jax.Array
    Q: jax.Array
    R: jax.Array


class StepInfo(NamedTuple):
    """Per-step diagnostics (not carried).

    Attributes:
        log_mode_probs: ``(*runs, M)`` posterior log mode probabilities (eq. 28).
        model_loglik: ``(*runs, M)`` innovation log-likelihood of each model (eq. 27).
        loglik_increment: ``(*runs,)`` ``log p(y_k | y_<k)`` of the mixture.
        mean: ``(n, *runs)`` combined estimate (eq. 30).
        cov: ``(n, n, *runs)`` combined covariance (eq. 31).
        health: ``(*runs,)`` int32 bit flags (``HEALTH_*``).
    """

    log_mode_probs: jax.Array
    model_loglik: jax.Array
    loglik_increment: jax.Array
    mean: jax.Array
    cov: jax.Array
    health: jax.Array


def log_normalize(log_w: jax.Array, axis: int = -1) -> tuple[jax.Array, jax.Array]:
    """Normalise log weights along ``axis``: returns ``(log_w - lse, lse)``.

    Safe when every weight is ``-inf`` (the weights are then returned unchanged and the
    normaliser is ``-inf``) and never produces NaN for finite or ``-inf`` inputs.
    """
    mx = jnp.max(log_w, axis=axis, keepdims=True)
    safe = jnp.where(jnp.isfinite(mx), mx, 0.0)
    shifted = log_w - safe
    log_s = jnp.log(jnp.sum(jnp.exp(shifted), axis=axis, keepdims=True))
    lse = log_s + safe
    ok = jnp.isfinite(lse)
    # Subtract in the shifted domain: with |max| > ~1e16 (an innovation of 1e8 sigma)
    # ``log_w - lse`` would lose ``log_s`` to rounding and return probabilities summing to M.
    out = jnp.where(ok, shifted - jnp.where(ok, log_s, 0.0), log_w)
    return out, jnp.squeeze(lse, axis)


def mix(mean: jax.Array, cov: jax.Array, log_mu: jax.Array, log_trans: jax.Array):
    """Interaction step, paper eqs. (15)-(17).

    Args:
        mean: ``(n, *runs, M)``.
        cov: ``(n, n, *runs, M)``.
        log_mu: ``(*runs, M)``.
        log_trans: ``(M, M)`` or ``(*runs, M, M)``.

    Returns:
        ``(x0, P0, log_c)``: mixed means ``(n, *runs, M)`` and covariances
        ``(n, n, *runs, M)`` of each model, and the log predicted mode probabilities
        ``log c_j`` ``(*runs, M)``.
    """
    M = mean.shape[-1]
    if M <= PAIRWISE_MAX_MODELS:
        # log c_j = s + log sum_i p_ij exp(log mu_i - s), one shift s = max_i log mu_i for
        # every j (M exponentials instead of M^2).  The largest term exp(log mu_i - s) is
        # 1, so c_j underflows only if every p_ij mu_i / mu_max does, i.e. below 1e-308.
        top = jnp.max(log_mu, axis=-1, keepdims=True)
        shift = jnp.where(jnp.isfinite(top), top, 0.0)
        mu_s = jnp.exp(log_mu - shift)  # (*runs, M), max entry 1
        t = jnp.exp(log_trans) * mu_s[..., :, None]  # (*runs, Mi, Mj)
        c = jnp.sum(t, axis=-2)  # (*runs, Mj) scaled predicted probabilities
        ok = c > 0
        inv_c = 1.0 / jnp.where(ok, c, 1.0)
        log_c = jnp.where(ok, jnp.log(jnp.where(ok, c, 1.0)) + shift, -jnp.inf)
        w = jnp.where(ok[..., None, :], t * inv_c[..., None, :], jnp.eye(M, dtype=mean.dtype))
        # Eq. (17) with the spread-of-means term per pair (i, j): exact, no cancellation
        # even when the means are far apart (after an outlier, say).
        x0 = jnp.sum(mean[..., :, None] * w, axis=-2)
        dx = mean[..., :, None] - x0[..., None, :]  # (n, *runs, Mi, Mj)
        P0 = jnp.sum(w * (cov[..., :, None] + dx[:, None] * dx[None]), axis=-2)
        return x0, P0, log_c
    # Vectorised path for large banks (combinatorial IMM): weights (*runs, Mi, Mj).
    t = log_trans + log_mu[..., :, None]
    log_c = jax.nn.logsumexp(t, axis=-2)
    ok = jnp.isfinite(log_c)
    eye = jnp.eye(M, dtype=mean.dtype)
    w = jnp.where(ok[..., None, :], jnp.exp(t - jnp.where(ok, log_c, 0.0)[..., None, :]), eye)
    # Per-pair spreads would cost O(n^2 M^2) memory here; instead use the second-moment form
    # centred on the probability-weighted mean, which is exact algebraically and loses only
    # ~eps * spread^2 / P relative precision (fine unless the means differ by >1e6 sigma).
    ref = jnp.sum(jnp.exp(log_mu) * mean, axis=-1, keepdims=True)
    d = mean - ref  # (n, *runs, M)
    x0d = jnp.einsum("a...i,...ij->a...j", d, w)
    second = jnp.einsum("ab...i,...ij->ab...j", cov + d[:, None] * d[None, :], w)
    P0 = second - x0d[:, None] * x0d[None, :]
    return x0d + ref, P0, log_c


def combine(mean: jax.Array, cov: jax.Array, log_mu: jax.Array):
    """Combined estimate and covariance, paper eqs. (30)-(31), over the last (model) axis."""
    mu = jnp.exp(log_mu)
    xc = jnp.sum(mu * mean, axis=-1)
    d = mean - xc[..., None]
    Pc = jnp.sum(mu * (cov + d[:, None] * d[None, :]), axis=-1)
    return xc, Pc


def imm_step(
    dyn: Any,
    state: IMMState,
    cache: Any,
    params: IMMParams,
    u: jax.Array,
    y: jax.Array,
    *,
    active: jax.Array | None = None,
    gate: float | None = None,
    with_cov: bool = True,
) -> tuple[IMMState, StepInfo]:
    """One IMM cycle: mix, predict with ``u``, update with ``y``, re-weight, combine.

    Args:
        dyn: a dynamics object (:mod:`uimm_jax.engine.dynamics`).
        state: the carried :class:`IMMState`.
        cache: the dynamics cache of every model (from ``dyn.prepare``).
        params: :class:`IMMParams`.
        u: ``(p, *runs)`` input of this step (paper's ``u_k``).
        y: ``(m, *runs)`` measurement; NaN entries are missing.
        active: optional ``(*runs, M)`` boolean mask; inactive models get probability 0.
        gate: optional chi-square gate on the normalised innovation squared: when even the
            best-fitting active model has ``e' S^-1 e > gate``, the measurement is treated
            as missing for the whole bank (an outlier), and the step is flagged.
        with_cov: compute the combined covariance (eq. 31) for the info.

    Returns:
        ``(new_state, info)``.
    """
    dtype = state.mean.dtype
    nb = state.log_mode_probs.ndim  # batch axes (runs..., models)
    x0, P0, log_c = mix(state.mean, state.cov, state.log_mode_probs, params.log_transition)
    x_pred, F = dyn.predict(cache, x0, u[..., None])
    P_pred = kf_predict_cov(F, P0, bk.align(params.Q, 2, nb))
    y_pred, H = dyn.observe(cache, x_pred)
    floor = float(jnp.finfo(dtype).tiny) ** 0.5
    res = kf_update(x_pred, P_pred, y[..., None], y_pred, H, bk.align(params.R, 2, nb), floor)
    x_new, P_new, ll, nis, repaired = res.mean, res.cov, res.loglik, res.nis, res.repaired
    if active is None:
        active = jnp.ones(state.log_mode_probs.shape, bool)
    health = jnp.zeros(state.log_mode_probs.shape[:-1], jnp.int32)
    health |= jnp.where(jnp.any(repaired & active, axis=-1), HEALTH_COV_REPAIRED, 0)
    missing = jnp.any(~jnp.isfinite(y), axis=0)
    health |= jnp.where(missing, HEALTH_MISSING, 0)
    if gate is not None:
        best = jnp.min(jnp.where(active, nis, jnp.inf), axis=-1)
        reject = best > gate  # (*runs,)
        rj = reject[..., None]
        x_new = jnp.where(rj, x_pred, x_new)
        P_new = jnp.where(rj, P_pred, P_new)
        ll = jnp.where(rj, 0.0, ll)
        health |= jnp.where(reject, HEALTH_GATED, 0)
    # Non-finite guard: a model whose update is not finite keeps its previous posterior.
    finite = (
        jnp.isfinite(ll)
        & jnp.all(jnp.isfinite(x_new), axis=0)
        & jnp.all(jnp.isfinite(P_new), axis=(0, 1))
    )
    health |= jnp.where(jnp.any(~finite & active, axis=-1), HEALTH_NONFINITE, 0)
    x_new = jnp.where(finite, x_new, state.mean)
    P_new = jnp.where(finite, P_new, state.cov)
    very_negative = jnp.asarray(jnp.finfo(dtype).min / 4, dtype)
    ll = jnp.where(finite, ll, very_negative)
    # Mode probabilities, eq. (28), in log space.
    log_post = jnp.where(active, ll + log_c, -jnp.inf)
    log_mu, lse = log_normalize(log_post)
    # If nothing is possible (every active model has c_j = 0), keep the previous probs.
    log_mu = jnp.where(jnp.isfinite(lse)[..., None], log_mu, state.log_mode_probs)
    xc, Pc = combine(x_new, P_new, log_mu)
    info = StepInfo(
        log_mode_probs=log_mu,
        model_loglik=ll,
        loglik_increment=jnp.where(jnp.isfinite(lse), lse, very_negative),
        mean=xc,
        cov=Pc if with_cov else jnp.zeros((0,), dtype),
        health=health,
    )
    return IMMState(x_new, P_new, log_mu), info
