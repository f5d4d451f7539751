"""Kalman filter predict/update, written once for a whole bank (paper eqs. 18-27).

Bank arrays carry the matrix indices first and the batch (models, then runs) last:
``x (n, *batch)``, ``P (n, n, *batch)``.  Every product is a block reduction
(:mod:`uimm_jax.engine._block`), so one call filters every model of every run.
:func:`ekf_predict` and :func:`ekf_update` are the user-facing single-model versions on
ordinary arrays, with Jacobians from ``jax.jacfwd``.

The update works with the inverse Cholesky factor of the innovation covariance,
``S = L L'`` (eq. 24), never with ``S^-1`` or an explicit gain inverse: ``v = L^-1 e``
gives the Mahalanobis term ``v'v`` and, with ``W = P H' L^-T``, the mean update
``K e = W v`` and the covariance of eq. (26), ``P - K S K' = P - W W'`` (symmetric entry
for entry).  The log-determinant comes from the pivots of the factorisation.  A filter for
which ``P - W W'`` is not trustworthy uses the Joseph form
``(I - K H) P (I - K H)' + K R K'`` instead (symmetric PSD for any gain), selected per
filter, so that no filter depends on the rest of its batch (a ``lax.cond`` skips the
Joseph arithmetic on the steps where no filter of the batch needs it):

* when a pivot of ``S`` had to be floored (``S`` numerically singular: duplicated or
  noise-free sensors), ``P - W W'`` can lose positive semi-definiteness;
* when the update removes nearly all of a variance (a precise sensor against a vague
  prior: the actuator's first steps, R = 1e-12 against P0 = 0.1 I, leave ~1e-11 of the
  prior) the subtraction cancels (relative error ~1e-3, measured): the Joseph form is
  used whenever a posterior variance falls below :data:`CANCELLATION_RATIO` of its prior
  (or is negative or NaN).

Reverse mode: :func:`kf_update` is a ``jax.custom_vjp`` whose backward pass is written
from the update's matrix differentials (:func:`_update_backward`) in block products: the
covariance is differentiated as the Joseph form (stable whichever form the forward pass
used), and neither the ``lax.cond`` nor the unrolled factorisation is differentiated.  The
forward pass is unchanged.

A non-finite measurement channel is *missing*: its row of ``H`` and its innovation are
zeroed and its variance set to one, which leaves the other channels' update exact and
contributes nothing to the log-likelihood.  An ``accept`` predicate (the IMM's innovation
gate) can reject a measurement after the innovation is known: the rejected filters keep
their prediction, with a zero likelihood term.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine import _block as bk

__all__ = ["UpdateResult", "ekf_predict", "ekf_update", "kf_predict_cov", "kf_update"]

LOG_2PI = math.log(2.0 * math.pi)

# The update uses P - W W' only while every posterior variance keeps at least this
# fraction of its prior (else the subtraction cancels: see the module docstring).
CANCELLATION_RATIO = 1e-2


class UpdateResult(NamedTuple):
    """Outcome of a measurement update for a bank (batch = runs..., models).

    Attributes:
        mean: ``(n, *batch)`` posterior mean.
        cov: ``(n, n, *batch)`` posterior covariance.
        loglik: ``(*batch)`` ``log N(e; 0, S)`` of the observed channels (eq. 27, log space).
        nis: ``(*batch)`` normalised innovation squared ``e' S^-1 e`` (for gating).
        repaired: ``(*batch)`` true where ``S`` was not numerically positive definite.
        num_observed: ``(*batch)`` number of observed (finite) channels.
        accepted: the ``accept`` predicate's verdict (see :func:`kf_update`), or ``None``
            when no predicate was given.
        nis_channels: ``(m, *batch)`` each channel's own normalised innovation squared
            ``e_i^2 / S_ii`` (``chi^2_1`` when the model and its noise are the data's,
            whatever the correlation between channels; 0 on a missing channel).
    """

    mean: jax.Array
    cov: jax.Array
    loglik: jax.Array
    nis: jax.Array
    repaired: jax.Array
    num_observed: jax.Array
    accepted: jax.Array | None = None
    nis_channels: jax.Array | None = None


def kf_predict_cov(F, P: jax.Array, Q: jax.Array) -> jax.Array:
    """Predicted covariance ``F P F' + Q`` (eq. 22) of a bank; ``Q`` broadcasts.

    The product is made exactly symmetric by mirroring its lower triangle.
    """
    return bk.mirror_lower(bk.mmt(bk.mm(F, P), F)) + Q


@jax.custom_vjp
def _predict_cov(F, P: jax.Array, Q: jax.Array) -> jax.Array:
    """:func:`kf_predict_cov` with its reverse mode by hand (the IMM step's default).

    With ``X = F P F'`` and ``G`` the cotangent of ``mirror_lower(X)`` carried back to
    ``X``: ``P_bar = F' G F``, ``F_bar = G F P' + G' F P`` and ``Q_bar = G`` (summed over
    its broadcast axes).  The residuals are ``F``, and ``P`` only when ``F`` has a
    tangent (an EKF's Jacobian); reverse mode through the block products stored ``F``
    twice more, broadcast for each product.
    """
    return kf_predict_cov(F, P, Q)


def _predict_cov_fwd(F, P, Q):
    out = kf_predict_cov(F.value, P.value, Q.value)
    shapes = (jnp.shape(F.value), jnp.shape(P.value), jnp.shape(Q.value))
    return out, (F.value, P.value if F.perturbed else None, shapes)


def _predict_cov_bwd(res, g):
    F, P, (f_shape, p_shape, q_shape) = res
    if isinstance(g, jax.custom_derivatives.SymbolicZero):
        g = jnp.zeros(g.shape, g.dtype)
    g_X = bk._mirror_lower_bwd(None, g)[0]  # the cotangent of X = F P F'
    g_FP = bk.mm(g_X, F)  # of F P
    g_F = None
    if P is not None:
        g_F = _sum_to(bk.mmt(g_FP, P) + bk.mtm(g_X, bk.mm(F, P)), f_shape)
    return g_F, _sum_to(bk.mtm(F, g_FP), p_shape), _sum_to(g, q_shape)


_predict_cov.defvjp(_predict_cov_fwd, _predict_cov_bwd, symbolic_zeros=True)


def kf_update(
    x: jax.Array,
    P: jax.Array,
    y: jax.Array,
    y_pred: jax.Array,
    H,
    R,
    floor: float,
    accept: Callable[..., jax.Array] | None = None,
    accept_args: tuple = (),
) -> UpdateResult:
    """Measurement update of a bank (eqs. 21, 23-27).

    Args:
        x: ``(n, *batch)`` predicted mean.
        P: ``(n, n, *batch)`` predicted covariance.
        y: ``(m, ...)`` measurement broadcastable to ``(m, *batch)`` (non-finite = missing).
        y_pred: ``(m, *batch)`` predicted measurement ``h(x)``.
        H: ``(m, n, *batch)`` measurement Jacobian, or a constant NumPy ``(m, n)``.
        R: ``(m, m, ...)`` measurement noise covariance (broadcastable).
        floor: smallest admissible squared Cholesky pivot of ``S``.
        accept: optional ``accept(nis (*batch), *accept_args) -> bool`` (broadcasting to
            the batch): filters where it is false keep ``(x, P)`` and get a zero
            log-likelihood (a gate).  Masking the gain costs one select on ``W``;
            selecting the results afterwards cost 15-18% of an IMM step (measured).  It
            must not close over traced arrays (the update's reverse mode is a
            ``custom_vjp``): pass them in ``accept_args``.
        accept_args: arrays passed to ``accept`` after ``nis`` (not differentiated).

    Returns:
        An :class:`UpdateResult`.
    """
    const_H = isinstance(H, np.ndarray)  # a constant (C = I is then free in the algebra)

    def update(x, P, y, y_pred, H_arg, R, accept_args):
        H_ = H if const_H else H_arg
        return _update_forward(x, P, y, y_pred, H_, R, floor, accept, accept_args)

    args = tuple(jnp.asarray(a) for a in (x, P, y, y_pred))
    args += (None if const_H else jnp.asarray(H), jnp.asarray(R), tuple(accept_args))
    shapes = tuple(None if a is None else jnp.shape(a) for a in args[:6])

    def bwd(res, ct):
        g = _update_backward(res, ct, H if const_H else res.H, res.R, shapes)
        return g + (tuple(None for _ in accept_args),)

    fn = jax.custom_vjp(lambda *a: update(*a)[0])
    fn.defvjp(update, bwd)
    return fn(*args)


class _Residuals(NamedTuple):
    """What the update's reverse mode keeps of its forward pass (see :func:`_update_backward`)."""

    P: jax.Array
    H: jax.Array | None
    Linv: jax.Array
    W: jax.Array
    e: jax.Array
    valid: jax.Array
    keep: jax.Array | None
    R: jax.Array
    joseph: jax.Array
    S_diag: jax.Array


def _update_forward(x, P, y, y_pred, H, R, floor, accept, accept_args):
    """The update of :func:`kf_update` and the residuals of its reverse mode."""
    const_H = isinstance(H, np.ndarray)
    m = y_pred.shape[0]
    n = x.shape[0]
    valid = jnp.isfinite(y)  # (m, ...): the measurement's own shape, not the bank's
    e = jnp.where(valid, y - y_pred, 0.0)
    # Missing channels: zero their rows/columns of S and P H' and put 1 on S's diagonal.
    # The gain's column for such a channel is then exactly zero, so H and R need no
    # masking (and a constant H = I stays free).
    PHt = bk.mmt(P, H)  # (n, m, *batch)
    S = bk.mm(H, PHt) + R
    # The per-channel NIS's variances, read before the masking below (on a missing channel
    # e = 0, so the term is 0 either way): after it, uimm-est's step measured 1.04-1.07x.
    S_diag = jnp.maximum(bk.diagonal(S), floor)
    eye = np.eye(m).reshape((m, m) + (1,) * (S.ndim - 2))
    S = jnp.where(valid[:, None] & valid[None, :], S, eye.astype(S.dtype))
    PHt = jnp.where(valid[None, :], PHt, 0.0)
    Linv, logdet, repaired = bk.inv_cholesky(S, floor)
    v = bk.mv(Linv, e)  # L^-1 e: K e = W v and K S K' = W W'
    nis = jnp.sum(v * v, axis=0)
    nis_channels = e * e / S_diag
    num_obs = jnp.sum(valid, axis=0, dtype=jnp.int32)
    loglik = -0.5 * (nis + logdet) - (0.5 * LOG_2PI) * num_obs.astype(nis.dtype)
    W = bk.mmt(PHt, Linv)  # P H' L^-T, (n, m, *batch)
    keep = None
    if accept is not None:
        keep = accept(nis, *accept_args)
        W = jnp.where(keep, W, 0.0)  # K = 0: x and P stay as predicted
        loglik = jnp.where(keep, loglik, 0.0)
    x_new = x + bk.mv(W, v)
    WWt = bk.mmt(W, W)
    # P - W W' has a rounding error of ~eps * P_ii on entries of size P_new_ii: fine unless
    # the update removes nearly all of a variance (a precise sensor against a vague prior,
    # as in the actuator's first steps) or S needed repair; then the Joseph form is used.
    margin = (1.0 - CANCELLATION_RATIO) * bk.diagonal(P) - bk.diagonal(WWt)
    # Decided per filter: a filter's numbers never depend on the rest of its batch.
    use_joseph = repaired | ~jnp.all(margin >= 0.0, axis=0)  # a NaN margin counts too

    def standard(_):
        return P - WWt  # P - K S K' = P - W W', symmetric entry for entry

    def joseph(_):
        K = bk.mm(W, Linv)  # W L^-1 = P H' S^-1
        eye_n = np.eye(n).reshape((n, n) + (1,) * (P.ndim - 2)).astype(P.dtype)
        IKH = eye_n - bk.mm(K, H)
        return bk.sym(bk.mmt(bk.mm(IKH, P), IKH) + bk.mmt(bk.mm(K, R), K))

    def per_filter(_):
        return jnp.where(use_joseph, joseph(None), standard(None))

    # The choice is per filter, so that a run never depends on its batch-mates (a
    # batch-wide choice gave last-bit differences between batches of 16 and 32); the
    # lax.cond only skips the Joseph arithmetic on the (usual) steps where no filter of
    # the batch needs it.  Always computing both measured 1.27x against 1.11x the
    # reference step at one run, 1.66x against 1.28x at 64.
    P_new = jax.lax.cond(jnp.any(use_joseph), per_filter, standard, None)
    out = UpdateResult(x_new, P_new, loglik, nis, repaired, num_obs, keep, nis_channels)
    res = _Residuals(P, None if const_H else H, Linv, W, e, valid, keep, R, use_joseph, S_diag)
    return out, res


def _sum_to(g: jax.Array, shape: tuple) -> jax.Array:
    """Sum a cotangent over the axes its primal was broadcast along (NumPy rules)."""
    extra = g.ndim - len(shape)
    if extra:
        g = jnp.sum(g, axis=tuple(range(extra)))
    axes = tuple(i for i, (a, b) in enumerate(zip(g.shape, shape, strict=True)) if b == 1 != a)
    return jnp.sum(g, axis=axes, keepdims=True) if axes else g


def _update_backward(res: _Residuals, ct: UpdateResult, H, R, shapes):
    """Reverse mode of the update, written from its matrix differentials.

    With ``K = P H' S^-1``, ``A = I - K H``, ``a = S^-1 e`` and the (symmetrised)
    cotangent ``G`` of the posterior covariance:

    * ``P_new = A P A' + K R K'`` (both forms of the update compute this function), and
      its differential has no ``dK`` term (the gain is stationary), so the covariance
      contributes ``A' G A`` to ``P``, ``K' G K`` to ``R`` and ``-2 K' G A P`` to ``H``:
      the Joseph form's numerical stability, without its ``lax.cond``;
    * ``x_new = x + K e``: ``K_bar = x_bar e'`` reaches ``P`` as ``K_bar S^-1 H``, ``H``
      as ``S^-1 K_bar' P`` and ``S`` as ``-K' K_bar S^-1``;
    * ``nis = e' S^-1 e`` and ``loglik = -(nis + log det S) / 2``: ``e`` gets
      ``2 nis_bar a``, ``S`` gets ``-nis_bar a a' - loglik_bar S^-1 / 2``;
    * ``nis_channels_i = e_i^2 / S_ii``: ``e_i`` gets ``2 c_i e_i / S_ii`` and ``S_ii``
      ``-c_i e_i^2 / S_ii^2`` (``c`` its cotangent);
    * ``S = H P H' + R`` passes ``S_bar`` on as ``H' S_bar H``, ``S_bar`` and
      ``2 S_bar H P``.

    A gated filter has ``K = 0`` and no likelihood term; a missing channel's rows of
    ``S_bar`` and ``H_bar`` are zero.  Where pivots of ``S`` were floored (``repaired``)
    this is the gradient of the update with the repaired ``S`` (the floor's increment
    taken as a constant).  Block products only: with it (and
    :func:`uimm_jax.engine._block.mirror_lower`'s) the tuning gradient of paper simulation
    1 (1e5 samples, truth precomputed) went from 6.4x to 3.6x the loss's forward time.

    The covariance's ``K_bar`` term ``2 G (K S - P H')`` vanishes for the exact gain and
    is computed, under a ``lax.cond``, only for the filters whose forward pass took the
    Joseph form (there it cancels the rounding of ``I - K H`` to first order, or carries
    the repaired ``S``); the rest of ``K_bar`` is the rank-one ``x_bar e'``, whose products
    are outer products of vectors.  With ``C = I`` this halved the adjoint's block
    products (tuning gradient -2 to -4 %, ``benchmarks/README.md``).
    """
    P, _, Linv, W, e, valid, keep, _, joseph, S_diag = res
    n = P.shape[0]
    G = bk.sym(ct.cov)
    g_ll = ct.loglik if keep is None else jnp.where(keep, ct.loglik, 0.0)
    g_nis = ct.nis - 0.5 * g_ll
    K = bk.mm(W, Linv)  # P H' S^-1 (zero where gated)
    Sinv = bk.mtm(Linv, Linv)
    a = bk.mv(Sinv, e)  # zero on a missing channel (e is, and S's row is the identity's)
    eye_n = np.eye(n).reshape((n, n) + (1,) * (P.ndim - 2)).astype(P.dtype)
    A = eye_n - bk.mm(K, H)
    GA = bk.mm(G, A)
    vvalid = valid[:, None] & valid[None, :]
    # K_bar = x_bar e' from the mean: rank one, so its products with K and S^-1 are
    # outer products of vectors (K' K_bar S^-1 = (K' x_bar) a', K_bar S^-1 = x_bar a').
    xb = ct.mean if keep is None else jnp.where(keep, ct.mean, 0.0)
    Ktx = jnp.sum(K * xb[:, None], axis=0)  # K' x_bar, (m, *batch)
    c_e = ct.nis_channels * e / S_diag  # the per-channel NIS's terms (zero when unused)
    g_e = Ktx + (2.0 * g_nis) * a + 2.0 * c_e
    S_bar = Ktx[:, None] * a[None] + g_nis * (a[:, None] * a[None]) + (0.5 * g_ll) * Sinv
    m = e.shape[0]
    eye_m = np.eye(m, dtype=bool).reshape((m, m) + (1,) * (S_bar.ndim - 2))
    S_bar = S_bar + jnp.where(eye_m, (c_e * e / S_diag)[:, None], 0.0)
    S_bar = jnp.where(vvalid, -bk.sym(S_bar), 0.0)
    Hta = a if bk.is_identity(H) else jnp.sum(bk.align(H, 2, a.ndim - 1) * a[:, None], axis=0)
    g_P = bk.mtm(A, GA) + bk.mtm(H, bk.mm(S_bar, H)) + xb[:, None] * Hta[None]
    g_R = bk.mtm(K, bk.mm(G, K)) + S_bar
    g_e = jnp.where(valid, g_e, 0.0)
    x_s, P_s, y_s, yp_s, H_s, R_s = shapes
    g_H = None
    if H_s is not None:
        g_H = 2.0 * bk.mm(S_bar, H) + a[:, None] * xb[None] - 2.0 * bk.mtm(K, GA)
    # The covariance's gain term 2 G (K S - P H'), zero for the exact gain: where the
    # forward pass took the Joseph form (S repaired, or the update removing nearly all of
    # a variance, where 1 - K H carries rounding errors ~eps P / R) it is kept, per filter
    # and under a lax.cond taken only on the steps where some filter needs it; elsewhere it
    # is rounding noise against A' G A (every variance keeps >= 1% of its prior).
    mask = joseph & (True if keep is None else keep)

    def gain_term(_):
        Kc = 2.0 * (bk.mm(bk.mm(G, K), R) - bk.mmt(bk.mm(GA, P), H))
        Kc = jnp.where(valid[None, :] & mask, Kc, 0.0)  # K has no column for a missing channel
        KcSi = bk.mm(Kc, Sinv)
        Sc = jnp.where(vvalid, -bk.sym(bk.mtm(K, KcSi)), 0.0)
        dP = bk.mtm(H, bk.mm(Sc, H)) + bk.mm(KcSi, H)
        dH = None if H_s is None else 2.0 * bk.mm(Sc, H) + jnp.swapaxes(KcSi, 0, 1)
        return dP, Sc, dH

    def no_gain_term(_):
        dH = None if H_s is None else jnp.zeros_like(g_H)
        return jnp.zeros_like(g_P), jnp.zeros_like(g_R), dH

    dP, dR, dH = jax.lax.cond(jnp.any(mask), gain_term, no_gain_term, None)
    g_P = g_P + dP
    g_R = g_R + dR
    if H_s is not None:
        g_H = _sum_to(jnp.where(valid[:, None], bk.mm(g_H + dH, P), 0.0), H_s)
    return (
        _sum_to(ct.mean, x_s),
        _sum_to(g_P, P_s),
        _sum_to(g_e, y_s),
        _sum_to(-g_e, yp_s),
        g_H,
        _sum_to(g_R, R_s),
    )


def _floor_for(dtype) -> float:
    return float(jnp.finfo(dtype).tiny) ** 0.5


def ekf_predict(mean, cov, u, f, Q):
    """EKF prediction for one model (eqs. 18, 19, 22).

    Args:
        mean: ``(n,)`` posterior mean.
        cov: ``(n, n)`` posterior covariance.
        u: input passed to ``f``.
        f: ``f(x, u) -> x_next`` (close over parameters).
        Q: ``(n, n)`` process noise covariance.

    Returns:
        ``(mean_pred, cov_pred)``; the Jacobian is ``jax.jacfwd(f)`` at ``mean``.
    """
    mean = jnp.asarray(mean)
    F = jax.jacfwd(f)(mean, u)
    return f(mean, u), kf_predict_cov(F, jnp.asarray(cov), jnp.asarray(Q))


def ekf_update(mean, cov, y, h, R):
    """EKF measurement update for one model (eqs. 20, 21, 23-27).

    Args:
        mean: ``(n,)`` predicted mean.
        cov: ``(n, n)`` predicted covariance.
        y: ``(m,)`` measurement; NaN entries are missing channels.
        h: ``h(x) -> y_pred``.
        R: ``(m, m)`` measurement noise covariance.

    Returns:
        ``(mean, cov, loglik)`` (covariance as described in the module docstring).
    """
    mean = jnp.asarray(mean)
    H = jax.jacfwd(h)(mean)
    res = kf_update(
        mean,
        jnp.asarray(cov),
        jnp.asarray(y, mean.dtype),
        h(mean),
        H,
        jnp.asarray(R),
        _floor_for(mean.dtype),
    )
    return res.mean, res.cov, res.loglik
