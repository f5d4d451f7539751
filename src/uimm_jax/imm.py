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

from uimm_jax import _smallmat as sm
from uimm_jax.kalman import kf_predict_cov, kf_update

__all__ = ["IMMParams", "IMMState", "StepInfo", "imm_step", "log_normalize", "mix"]

UNROLL_MAX_MODELS = 16

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


def _lse_list(terms: list[jax.Array]) -> jax.Array:
    """Max-shifted log-sum-exp of a list of equally shaped arrays; all ``-inf`` -> ``-inf``."""
    mx = terms[0]
    for t in terms[1:]:
        mx = jnp.maximum(mx, t)
    safe = jnp.where(jnp.isfinite(mx), mx, 0.0)
    s = sum(jnp.exp(t - safe) for t in terms)
    return jnp.log(s) + safe


def log_normalize(log_w: jax.Array, axis: int = -1) -> tuple[jax.Array, jax.Array]:
    """Normalise log weights along ``axis``: returns ``(log_w - lse, lse)``.

    Safe when every weight is ``-inf`` (the weights are then returned unchanged and the
    normaliser is ``-inf``) and never produces NaN for finite or ``-inf`` inputs.
    """
    mx = jnp.max(log_w, axis=axis, keepdims=True)
    safe = jnp.where(jnp.isfinite(mx), mx, 0.0)
    lse = jnp.log(jnp.sum(jnp.exp(log_w - safe), axis=axis, keepdims=True)) + safe
    out = jnp.where(jnp.isfinite(lse), log_w - jnp.where(jnp.isfinite(lse), lse, 0.0), log_w)
    return out, jnp.squeeze(lse, axis)


def mix(mean: jax.Array, cov: jax.Array, log_mu: jax.Array, log_trans: jax.Array):
    """Interaction step, paper eqs. (15)-(17).

    Args:
        mean: ``(n, *runs, M)``.
        cov: ``(n, n, *runs, M)``.
        log_mu: ``(*runs, M)``.
        log_trans: ``(M, M)`` or ``(*runs, M, M)``.

    Returns:
        ``(x0, P0, log_c)``: mixed means and covariances as nested entries of shape
        ``(*runs, M)``, and the log predicted mode probabilities ``log c_j``.
    """
    n = mean.shape[0]
    M = mean.shape[-1]
    if M <= UNROLL_MAX_MODELS:
        terms = [log_trans[..., i, :] + log_mu[..., i : i + 1] for i in range(M)]
        log_c = _lse_list(terms)
        ok = jnp.isfinite(log_c)
        eye = jnp.eye(M, dtype=mean.dtype)
        w = [
            jnp.where(ok, jnp.exp(t - jnp.where(ok, log_c, 0.0)), eye[i])
            for i, t in enumerate(terms)
        ]
        w, log_c = sm.materialize((w, log_c))
        xs = [[mean[a][..., i : i + 1] for i in range(M)] for a in range(n)]
        x0 = [sum(w[i] * xs[a][i] for i in range(M)) for a in range(n)]
        dx = [[xs[a][i] - x0[a] for i in range(M)] for a in range(n)]
        P0 = [[None] * n for _ in range(n)]
        for a in range(n):
            for b in range(a, n):
                v = sum(w[i] * (cov[a, b][..., i : i + 1] + dx[a][i] * dx[b][i]) for i in range(M))
                P0[a][b] = v
                P0[b][a] = v
        return x0, P0, log_c
    # Vectorised path for large banks (combinatorial IMM): weights (*runs, Mi, Mj).
    t = log_trans + log_mu[..., :, None]
    log_c = jax.nn.logsumexp(t, axis=-2)
    ok = jnp.isfinite(log_c)
    eye = jnp.eye(M, dtype=mean.dtype)
    w = jnp.where(ok[..., None, :], jnp.exp(t - jnp.where(ok, log_c, 0.0)[..., None, :]), eye)
    # Centre on the probability-weighted mean to keep the spread-of-means term exact.
    ref = jnp.sum(jnp.exp(log_mu) * mean, axis=-1, keepdims=True)
    d = mean - ref  # (n, *runs, M)
    x0d = jnp.einsum("a...i,...ij->a...j", d, w)
    second = jnp.einsum("ab...i,...ij->ab...j", cov + d[:, None] * d[None, :], w)
    P0a = second - x0d[:, None] * x0d[None, :]
    x0a = x0d + ref
    return sm.from_array(x0a, 1), sm.from_array(P0a, 2), log_c


def combine(mean: list, cov: list, log_mu: jax.Array):
    """Combined estimate and covariance, paper eqs. (30)-(31); entries ``(*runs, M)``."""
    mu = jnp.exp(log_mu)
    n = len(mean)
    xc = [jnp.sum(mu * mean[a], axis=-1) for a in range(n)]
    d = [mean[a] - xc[a][..., None] for a in range(n)]
    Pc = [[None] * n for _ in range(n)]
    for a in range(n):
        for b in range(a, n):
            v = jnp.sum(mu * (cov[a][b] + d[a] * d[b]), axis=-1)
            Pc[a][b] = v
            Pc[b][a] = v
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
    q_pattern: tuple | None = None,
    r_pattern: tuple | None = None,
) -> tuple[IMMState, StepInfo]:
    """One IMM cycle: mix, predict with ``u``, update with ``y``, re-weight, combine.

    Args:
        dyn: a dynamics object (:mod:`uimm_jax.dynamics`).
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
        q_pattern: static non-zero pattern of ``Q`` (entries outside it are treated as
            structural zeros; see :func:`uimm_jax._smallmat.sparsity_pattern`).
        r_pattern: static non-zero pattern of ``R``.

    Returns:
        ``(new_state, info)``.
    """
    dtype = state.mean.dtype
    n = state.mean.shape[0]
    x0, P0, log_c = mix(state.mean, state.cov, state.log_mode_probs, params.log_transition)
    x0, P0, log_c = sm.materialize((x0, P0, log_c))
    u_e = [u[i][..., None] for i in range(u.shape[0])]
    y_e = [y[c][..., None] for c in range(y.shape[0])]
    x_pred, F = dyn.predict(cache, x0, u_e)
    P_pred = kf_predict_cov(F, P0, sm.from_array_pattern(params.Q, q_pattern))
    y_pred, H = dyn.observe(cache, x_pred)
    x_pred, P_pred, y_pred = sm.materialize((x_pred, P_pred, y_pred))
    floor = float(jnp.finfo(dtype).tiny) ** 0.5
    R = sm.from_array_pattern(params.R, r_pattern)
    res = kf_update(x_pred, P_pred, y_e, y_pred, H, R, floor)
    x_new, P_new, ll, nis, repaired = sm.materialize(
        (res.mean, res.cov, res.loglik, res.nis, res.repaired)
    )
    if active is None:
        active = jnp.ones(state.log_mode_probs.shape, bool)
    health = jnp.zeros(state.log_mode_probs.shape[:-1], jnp.int32)
    health |= jnp.where(jnp.any(repaired & active, axis=-1), HEALTH_COV_REPAIRED, 0)
    missing = jnp.zeros(health.shape, bool)
    for c in range(y.shape[0]):
        missing = missing | ~jnp.isfinite(y[c])
    health |= jnp.where(missing, HEALTH_MISSING, 0)
    if gate is not None:
        best = jnp.min(jnp.where(active, nis, jnp.inf), axis=-1)
        reject = best > gate  # (*runs,)
        rj = reject[..., None]
        x_new = [jnp.where(rj, xp, xn) for xp, xn in zip(x_pred, x_new, strict=True)]
        P_new = [
            [jnp.where(rj, pp, pn) for pp, pn in zip(rp, rn, strict=True)]
            for rp, rn in zip(P_pred, P_new, strict=True)
        ]
        ll = jnp.where(rj, 0.0, ll)
        health |= jnp.where(reject, HEALTH_GATED, 0)
    # Non-finite guard: a model whose update is not finite keeps its previous posterior.
    finite = jnp.isfinite(ll)
    for a in range(n):
        finite &= jnp.isfinite(x_new[a])
        for b in range(a, n):
            finite &= jnp.isfinite(P_new[a][b])
    health |= jnp.where(jnp.any(~finite & active, axis=-1), HEALTH_NONFINITE, 0)
    x_new = [jnp.where(finite, x_new[a], state.mean[a]) for a in range(n)]
    P_new = [[jnp.where(finite, P_new[a][b], state.cov[a, b]) for b in range(n)] for a in range(n)]
    very_negative = jnp.asarray(jnp.finfo(dtype).min / 4, dtype)
    ll = jnp.where(finite, ll, very_negative)
    # Mode probabilities, eq. (28), in log space.
    log_post = jnp.where(active, ll + log_c, -jnp.inf)
    log_mu, lse = log_normalize(log_post)
    # If nothing is possible (every active model has c_j = 0), keep the previous probs.
    log_mu = jnp.where(jnp.isfinite(lse)[..., None], log_mu, state.log_mode_probs)
    x_new, P_new, log_mu = sm.materialize((x_new, P_new, log_mu))
    xc, Pc = combine(x_new, P_new, log_mu)
    new_state = IMMState(
        sm.to_array(x_new, state.log_mode_probs.shape, dtype),
        sm.to_array(P_new, state.log_mode_probs.shape, dtype),
        log_mu,
    )
    batch = state.log_mode_probs.shape[:-1]
    info = StepInfo(
        log_mode_probs=log_mu,
        model_loglik=ll,
        loglik_increment=jnp.where(jnp.isfinite(lse), lse, very_negative),
        mean=sm.to_array(xc, batch, dtype),
        cov=sm.to_array(Pc, batch, dtype) if with_cov else jnp.zeros((0,), dtype),
        health=health,
    )
    return new_state, info
