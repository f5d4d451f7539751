"""One cycle of the interacting multiple model (IMM) estimator, paper eqs. (15)-(31).

Layout: the small axes lead and the batch trails -- the model axis first, then any Monte
Carlo run axes: ``mean`` is ``(n, M, *runs)``, ``cov`` is ``(n, n, M, *runs)``,
``log_mode_probs`` is ``(M, *runs)``.  Every product is one broadcast multiply and one
reduction over a leading axis (:mod:`uimm_jax.engine._block`), so XLA CPU emits packed
code over the trailing batch, and the whole time loop compiles into one kernel.  The
public :func:`uimm_jax.imm_filter` converts to and from the user-facing layout once,
outside the time loop.

Mode probabilities are kept as logarithms.  A model whose predicted probability is
exactly zero (an absorbing fault mode, a UIMM model masked out after a declaration) is
handled without ``0/0``: its mixing weights fall back to its own previous estimate, and
its probability stays ``-inf``.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine import _block as bk
from uimm_jax.engine.kalman import _predict_cov, kf_predict_cov, kf_update

__all__ = [
    "HEALTH_COV_REPAIRED",
    "HEALTH_GATED",
    "HEALTH_MISSING",
    "HEALTH_NONFINITE",
    "IMMParams",
    "IMMState",
    "StepInfo",
    "combine",
    "imm_step",
    "log_normalize",
    "mix",
]

# Health flag bits reported per step.
HEALTH_COV_REPAIRED = 1  # an innovation covariance was not numerically PD: pivots floored
HEALTH_NONFINITE = 2  # a non-finite value was caught and replaced
HEALTH_GATED = 4  # the measurement was rejected by the innovation gate
HEALTH_MISSING = 8  # at least one measurement channel was missing (NaN)

# Up to this many models the mixing covariance (eq. 17) sums per-pair spreads,
# O(n^2 M^2) work and memory per run; larger (combinatorial) banks use the
# second-moment form (see :func:`mix`).
PAIRWISE_MAX_MODELS = 16


class IMMState(NamedTuple):
    """Carried IMM state (model axis first, run axes last).

    Attributes:
        mean: ``(n, M, *runs)`` per-model posterior means.
        cov: ``(n, n, M, *runs)`` per-model posterior covariances.
        log_mode_probs: ``(M, *runs)`` log mode probabilities (``-inf`` = impossible).
    """

    mean: jax.Array
    cov: jax.Array
    log_mode_probs: jax.Array


class IMMParams(NamedTuple):
    """Differentiable parameters of an IMM step.

    Attributes:
        log_transition: ``(M, M)`` (or ``(M, M, *runs)``) log of the transition matrix,
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
        log_mode_probs: ``(M, *runs)`` posterior log mode probabilities (eq. 28).
        model_loglik: ``(M, *runs)`` innovation log-likelihood of each model (eq. 27).
        loglik_increment: ``(*runs,)`` ``log p(y_k | y_<k)`` of the mixture.
        mean: ``(n, *runs)`` combined estimate (eq. 30).
        cov: ``(n, n, *runs)`` combined covariance (eq. 31), or ``(0,)`` when not asked.
        health: ``(*runs,)`` int32 bit flags (``HEALTH_*``).
        nis: ``(M, *runs)`` each model's normalised innovation squared ``e' S^-1 e`` over
            the observed channels (the quadratic term of eq. 27; 0 when none is observed):
            ``chi^2`` with as many degrees of freedom as observed channels when the
            model and its noise covariances are the data's.
        nis_channels: ``(m, M, *runs)`` each model's normalised innovation squared per
            channel, ``e_i^2 / S_ii`` (0 on a missing channel): ``chi^2_1`` on each
            channel under the same conditions, so that a channel whose noise is set
            wrong stands out.
    """

    log_mode_probs: jax.Array
    model_loglik: jax.Array
    loglik_increment: jax.Array
    mean: jax.Array
    cov: jax.Array
    health: jax.Array
    nis: jax.Array
    nis_channels: jax.Array


def log_normalize(log_w: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Normalise log weights over the leading (model) axis: ``(log_w - lse, lse)``.

    Safe when every weight is ``-inf`` (the weights are then returned unchanged and the
    normaliser is ``-inf``) and never produces NaN for finite or ``-inf`` inputs.
    """
    mx = jnp.max(log_w, axis=0, keepdims=True)
    safe = jnp.where(jnp.isfinite(mx), mx, 0.0)
    shifted = log_w - safe
    log_s = jnp.log(jnp.sum(jnp.exp(shifted), axis=0, keepdims=True))
    ok = jnp.isfinite(log_s)
    # Subtract in the shifted domain: with |max| > ~1e16 (an innovation of 1e8 sigma)
    # ``log_w - lse`` would lose ``log_s`` to rounding and return probabilities summing to M.
    out = jnp.where(ok, shifted - jnp.where(ok, log_s, 0.0), log_w)
    return out, (log_s + safe)[0]


# The time loop's log_normalize (eq. 28), with its reverse mode by hand: with p = exp(out)
# (zero where a weight is -inf, and everywhere when all are), d out_i = d w_i - sum_k p_k
# d w_k and d lse = sum_k p_k d w_k, so w_bar = out_bar + p (lse_bar - sum out_bar).  The
# residual is the output alone; reverse mode through the formulas kept 10 arrays (the
# shift, its masks, the exponentials) per step and differentiated the max-shift, whose
# derivative is exactly zero.
_log_normalize_vjp = jax.custom_vjp(log_normalize)


def _log_normalize_fwd(log_w):
    out, lse = log_normalize(log_w)
    return (out, lse), out


def _log_normalize_bwd(out, ct):
    g_out, g_lse = ct
    return (g_out + jnp.exp(out) * (g_lse - jnp.sum(g_out, axis=0)),)


_log_normalize_vjp.defvjp(_log_normalize_fwd, _log_normalize_bwd)


def _keep_finite_select(finite, x_new, P_new, ll, mean, cov, very_negative):
    """The non-finite guard of :func:`imm_step`: a model keeps its previous posterior."""
    return (
        jnp.where(finite, x_new, mean),
        jnp.where(finite, P_new, cov),
        jnp.where(finite, ll, very_negative),
    )


# Its reverse mode keeps the (M, *runs) mask alone, where reverse mode through the selects
# stored them broadcast to the mean's and the covariance's shapes.
_keep_finite = jax.custom_vjp(_keep_finite_select)


def _keep_finite_fwd(finite, x_new, P_new, ll, mean, cov, very_negative):
    return _keep_finite_select(finite, x_new, P_new, ll, mean, cov, very_negative), finite


def _keep_finite_bwd(finite, ct):
    g_x, g_P, g_ll = ct
    keep = (jnp.where(finite, g_x, 0.0), jnp.where(finite, g_P, 0.0), jnp.where(finite, g_ll, 0.0))
    old = (jnp.where(finite, 0.0, g_x), jnp.where(finite, 0.0, g_P))
    return (None, *keep, *old, None)


_keep_finite.defvjp(_keep_finite_fwd, _keep_finite_bwd)


def mix(mean: jax.Array, cov: jax.Array, log_mu: jax.Array, log_trans: jax.Array):
    """Interaction step, paper eqs. (15)-(17).

    Args:
        mean: ``(n, M, *runs)``.
        cov: ``(n, n, M, *runs)``.
        log_mu: ``(M, *runs)``.
        log_trans: ``(M, M)`` or ``(M, M, *runs)``.

    Returns:
        ``(x0, P0, log_c)``: mixed means ``(n, M, *runs)`` and covariances
        ``(n, n, M, *runs)`` of each model, and the log predicted mode probabilities
        ``log c_j`` ``(M, *runs)``.
    """
    M = log_mu.shape[0]
    nb = log_mu.ndim - 1
    trans = bk.align(jnp.exp(log_trans), 2, nb)
    eye = np.eye(M).reshape((M, M) + (1,) * nb)
    if M > PAIRWISE_MAX_MODELS:
        return _mix_large(mean, cov, log_mu, log_trans, eye)
    # c_j = s sum_i p_ij exp(log mu_i - s), one shift s = max_i log mu_i for every j
    # (M exponentials, not M^2).  The largest term exp(log mu_i - s) is 1, so c_j
    # underflows only if every p_ij mu_i / mu_max does, i.e. below 1e-308.
    return _mix_pairwise(mean, cov, log_mu, trans)


@jax.custom_vjp
def _mix_pairwise(mean, cov, log_mu, trans):
    """Eqs. (15)-(17) with per-pair spreads (:func:`mix`); reverse mode by hand."""
    return _mix_pairwise_fwd(mean, cov, log_mu, trans)[0]


def _mix_pairwise_fwd(mean, cov, log_mu, trans):
    top = jnp.max(log_mu, axis=0, keepdims=True)
    shift = jnp.where(jnp.isfinite(top), top, 0.0)
    e = jnp.exp(log_mu - shift)
    t = trans * e[:, None]  # (Mi, Mj, *runs)
    c = jnp.sum(t, axis=0)
    ok = c > 0
    w = t * (1.0 / jnp.where(ok, c, 1.0))  # a zero column where c_j = 0
    log_c = jnp.where(ok, jnp.log(jnp.where(ok, c, 1.0)) + shift, -jnp.inf)
    x0 = jnp.sum(w * mean[:, :, None], axis=1)  # (n, Mj, *runs)
    # Eq. (17) with the spread-of-means term per pair (i, j): exact, no cancellation
    # even when the means are far apart (after an outlier, say).
    d = mean[:, :, None] - x0[:, None]  # (n, Mi, Mj, *runs)
    P0 = jnp.sum(w * (cov[:, :, :, None] + d[:, None] * d[None]), axis=2)
    # A model no other can reach (c_j = 0) keeps its own estimate.  Selecting here, on
    # the mixed estimates, keeps the pairwise sums free of selects (measured 25% of a
    # step at 64 runs when the fallback sat in the weights).
    out = (jnp.where(ok, x0, mean), jnp.where(ok, P0, cov), log_c)
    return out, (mean, cov, trans, e, c, w, x0)


def _mix_pairwise_bwd(res, ct):
    """Reverse mode of the pairwise mixing, from its differentials.

    With ``d_ij = x_i - x0_j`` and the cotangents ``G_j`` of ``P0_j``, ``g_j`` of
    ``x0_j`` and ``l_j`` of ``log c_j``: ``P_i`` gets ``sum_j w_ij G_j``; ``x_i`` gets
    ``sum_j w_ij ((G_j + G_j') d_ij + g_j)``; ``w_ij`` gets ``<G_j, P_i> + d_ij' G_j d_ij
    + g_j' x_i``.  ``P0_j`` is stationary in ``x0_j`` (``sum_i w_ij d_ij = 0``), so the
    spread passes nothing through ``x0``.  Then ``w = t / c`` and ``log c = log(sum_i
    t_ij) + s`` give ``t_bar_ij = (w_bar_ij - sum_k w_kj w_bar_kj + l_j) / c_j``, and
    ``t_ij = p_ij exp(log mu_i - s)`` (the shift ``s`` cancels) the transition and mode
    probability cotangents.  No pairwise residual is stored: the pairwise terms are
    formed again here from the inputs, ``w`` and ``x0``.
    """
    mean, cov, trans, e, c, w, x0 = res
    g_x, g_P, g_lc = ct
    ok = c > 0
    g_x0 = jnp.where(ok, g_x, 0.0)
    g_P0 = jnp.where(ok, g_P, 0.0)
    d = mean[:, :, None] - x0[:, None]  # (n, Mi, Mj, *runs)
    gs = g_P0 + jnp.swapaxes(g_P0, 0, 1)
    gd = jnp.sum(gs[:, :, None] * d[None], axis=1)  # (G_j + G_j') d_ij, (n, Mi, Mj, *runs)
    g_w = (
        jnp.sum(g_P0[:, :, None] * cov[:, :, :, None], axis=(0, 1))
        + 0.5 * jnp.sum(d * gd, axis=0)
        + jnp.sum(g_x0[:, None] * mean[:, :, None], axis=0)
    )
    g_mean = jnp.where(ok, 0.0, g_x) + jnp.sum(w * (gd + g_x0[:, None]), axis=2)
    g_cov = jnp.where(ok, 0.0, g_P) + jnp.sum(w * g_P0[:, :, None], axis=3)
    inv_c = 1.0 / jnp.where(ok, c, 1.0)
    g_t = (g_w - jnp.sum(w * g_w, axis=0) + jnp.where(ok, g_lc, 0.0)) * inv_c
    g_trans = g_t * e[:, None]
    axes = tuple(i for i in range(2, g_trans.ndim) if trans.shape[i] == 1 != g_trans.shape[i])
    g_trans = jnp.sum(g_trans, axis=axes, keepdims=True) if axes else g_trans
    g_log_mu = jnp.sum(g_t * trans, axis=1) * e
    return g_mean, g_cov, g_log_mu, g_trans


_mix_pairwise.defvjp(_mix_pairwise_fwd, _mix_pairwise_bwd)


def _mix_large(mean, cov, log_mu, log_trans, eye):
    """Eqs. (15)-(17) for large (combinatorial) banks in the second-moment form.

    Per-pair spreads would cost O(n^2 M^2) memory; the second moment centred on the
    probability-weighted mean is exact algebraically and loses only ``~eps spread^2 / P``
    relative precision (fine unless the means differ by more than ~1e6 sigma).
    """
    nb = log_mu.ndim - 1
    t = bk.align(log_trans, 2, nb) + log_mu[:, None]  # (Mi, Mj, *runs)
    mx = jnp.max(t, axis=0, keepdims=True)
    safe = jnp.where(jnp.isfinite(mx), mx, 0.0)
    log_c = jnp.log(jnp.sum(jnp.exp(t - safe), axis=0)) + safe[0]
    ok = jnp.isfinite(log_c)
    w = jnp.where(ok, jnp.exp(t - jnp.where(ok, log_c, 0.0)), eye.astype(t.dtype))
    ref = jnp.sum(jnp.exp(log_mu) * mean, axis=1, keepdims=True)
    d = mean - ref  # (n, M, *runs)
    x0d = jnp.einsum("ai...,ij...->aj...", d, w)
    second = jnp.einsum("abi...,ij...->abj...", cov + d[:, None] * d[None], w)
    P0 = second - x0d[:, None] * x0d[None]
    return x0d + ref, P0, log_c


def combine(mean: jax.Array, cov: jax.Array, log_mu: jax.Array):
    """Combined estimate and covariance, paper eqs. (30)-(31), over the model axis.

    The covariance is summed for its lower triangle only, one reduction over the model
    axis per entry, and mirrored, so it is symmetric by construction.  The per-model
    covariances are symmetric entry for entry (:func:`uimm_jax.engine.kalman.kf_update`),
    so this equals the full block sum (measured identical on the actuator bank), and
    ``imm_filter`` measured 2-8% faster with it (M = 4, n = 3; the same speed at n = 8 and
    16; ``benchmarks/README.md``).
    """
    mu = jnp.exp(log_mu)
    xc = jnp.sum(mu * mean, axis=1)
    d = mean - xc[:, None]
    n = mean.shape[0]
    low = [
        [jnp.sum(mu * (cov[i, j] + d[i] * d[j]), axis=0) for j in range(i + 1)] for i in range(n)
    ]
    Pc = jnp.stack([jnp.stack([low[max(i, j)][min(i, j)] for j in range(n)]) for i in range(n)])
    return xc, Pc


def _gate_accept(gate: float, nis: jax.Array, active: jax.Array | None = None) -> jax.Array:
    """The innovation gate's verdict per run (``True``: the sample is used).

    The sample is rejected for every model of a run when even the best-fitting active
    model sees it beyond the gate; NaN is left to the finite guard.
    """
    nis = nis if active is None else jnp.where(active, nis, jnp.inf)
    return ~(jnp.min(nis, axis=0) > gate)


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
        dyn: a dynamics object (:class:`uimm_jax.engine.dynamics.Dynamics`).
        state: the carried :class:`IMMState`.
        cache: the dynamics cache of every model (from ``dyn.prepare``).
        params: :class:`IMMParams`.
        u: ``(p, *runs)`` input of this step (paper's ``u_k``).
        y: ``(m, *runs)`` measurement; NaN entries are missing.
        active: optional ``(M, *runs)`` boolean mask; inactive models get probability 0.
        gate: optional chi-square gate on the normalised innovation squared: when even the
            best-fitting active model has ``e' S^-1 e > gate``, the measurement is treated
            as missing for the whole bank (an outlier), and the step is flagged.
        with_cov: compute the combined covariance (eq. 31) for the info.

    Returns:
        ``(new_state, info)``.
    """
    dtype = state.mean.dtype
    nb = state.log_mode_probs.ndim  # batch axes (models, runs...)
    x0, P0, log_c = mix(state.mean, state.cov, state.log_mode_probs, params.log_transition)
    x_pred, F = dyn.predict(cache, x0, u[:, None])
    # A dynamics object whose Jacobian has a structure may predict the covariance itself.
    # (A constant NumPy F keeps the block algebra's trace-time shortcuts: no custom_vjp.)
    default = kf_predict_cov if isinstance(F, np.ndarray) else _predict_cov
    predict_cov = getattr(dyn, "predict_cov", default)
    P_pred = predict_cov(F, P0, bk.align(params.Q, 2, nb))
    y_pred, H = dyn.observe(cache, x_pred)
    floor = float(jnp.finfo(dtype).tiny) ** 0.5
    accept, accept_args = None, ()
    if gate is not None:
        accept = functools.partial(_gate_accept, float(gate))
        accept_args = () if active is None else (active,)
    R = bk.align(params.R, 2, nb)
    res = kf_update(x_pred, P_pred, y[:, None], y_pred, H, R, floor, accept, accept_args)
    x_new, P_new, ll = res.mean, res.cov, res.loglik
    repaired = res.repaired if active is None else res.repaired & active
    health = jnp.where(jnp.any(repaired, axis=0), HEALTH_COV_REPAIRED, 0)
    health |= jnp.where(jnp.any(~jnp.isfinite(y), axis=0), HEALTH_MISSING, 0)
    if gate is not None:
        health |= jnp.where(res.accepted, 0, HEALTH_GATED)
    # Non-finite guard: a model whose update is not finite keeps its previous posterior.
    finite = (
        jnp.isfinite(ll)
        & jnp.all(jnp.isfinite(x_new), axis=0)
        & jnp.all(jnp.isfinite(P_new), axis=(0, 1))
    )
    bad = ~finite if active is None else ~finite & active
    health |= jnp.where(jnp.any(bad, axis=0), HEALTH_NONFINITE, 0)
    very_negative = jnp.asarray(jnp.finfo(dtype).min / 4, dtype)
    x_new, P_new, ll = _keep_finite(finite, x_new, P_new, ll, state.mean, state.cov, very_negative)
    # Mode probabilities, eq. (28), in log space.
    log_post = ll + log_c if active is None else jnp.where(active, ll + log_c, -jnp.inf)
    log_mu, lse = _log_normalize_vjp(log_post)
    # If nothing is possible (every active model has c_j = 0), keep the previous probs.
    log_mu = jnp.where(jnp.isfinite(lse), log_mu, state.log_mode_probs)
    xc, Pc = combine(x_new, P_new, log_mu)
    info = StepInfo(
        log_mode_probs=log_mu,
        model_loglik=ll,
        loglik_increment=jnp.where(jnp.isfinite(lse), lse, very_negative),
        mean=xc,
        cov=Pc if with_cov else jnp.zeros((0,), dtype),
        health=health.astype(jnp.int32),
        nis=res.nis,
        nis_channels=res.nis_channels,
    )
    return IMMState(x_new, P_new, log_mu), info
