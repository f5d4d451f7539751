"""Kalman filter predict/update, written once for a whole bank (paper eqs. 18-27).

The functions work on nested-list matrices (:mod:`uimm_jax._smallmat`) whose entries are
arrays of the batch shape (runs..., models), so one call filters every model of every run.
:func:`ekf_predict` and :func:`ekf_update` are the user-facing single-model versions on
ordinary arrays, with Jacobians from ``jax.jacfwd``.

Conventions: the update uses a Cholesky factor of the innovation covariance ``S`` for the
gain, the log-determinant and the Mahalanobis term (never an explicit inverse), and the
Joseph form ``P = (I - K H) P (I - K H)' + K R K'`` (eq. 26 written so it stays symmetric
PSD).  A non-finite measurement channel is *missing*: its row of ``H`` and its innovation
are zeroed and its variance set to one, which leaves the other channels' update exact and
contributes nothing to the log-likelihood.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from uimm_jax import _smallmat as sm

__all__ = ["UpdateResult", "ekf_predict", "ekf_update", "kf_predict_cov", "kf_update"]

LOG_2PI = math.log(2.0 * math.pi)


class UpdateResult(NamedTuple):
    """Outcome of a measurement update for a bank (entries have the batch shape).

    Attributes:
        mean: posterior mean (list of n entries).
        cov: posterior covariance (n x n nested entries).
        loglik: ``log N(e; 0, S)`` of the observed channels (eq. 27 in log space).
        nis: normalised innovation squared ``e' S^-1 e`` (for gating).
        repaired: true where ``S`` was not numerically positive definite.
        num_observed: number of observed (finite) channels.
    """

    mean: list
    cov: list
    loglik: jax.Array
    nis: jax.Array
    repaired: jax.Array
    num_observed: jax.Array


def kf_predict_cov(F: list, P: list, Q: list) -> list:
    """Predicted covariance ``F P F' + Q`` (eq. 22), symmetric by construction."""
    return sm.add(sm.quad_sym(F, P), Q)


def kf_update(
    x: list, P: list, y: list, y_pred: list, H: list, R: list, floor: float
) -> UpdateResult:
    """Measurement update of a bank (eqs. 21, 23-27).

    Args:
        x: predicted mean, n entries.
        P: predicted covariance, n x n.
        y: measurement, m entries (non-finite = missing channel).
        y_pred: predicted measurement ``h(x)``, m entries.
        H: measurement Jacobian, m x n.
        R: measurement noise covariance, m x m.
        floor: smallest admissible squared Cholesky pivot of ``S``.

    Returns:
        An :class:`UpdateResult`.
    """
    m = len(y)
    n = len(x)
    valid = [jnp.isfinite(yc) for yc in y]
    e = [jnp.where(v, yc - yp, 0.0) for v, yc, yp in zip(valid, y, y_pred, strict=True)]
    # Missing channels: zero their rows/columns of S and P H' and put 1 on S's diagonal.
    # Then the gain's column for that channel is exactly zero, so H and R themselves need no
    # masking (and structural zeros/ones of a constant H stay folded at trace time).
    PHt = sm.matmul(P, sm.transpose(H))  # n x m
    S = sm.add(sm.quad_sym(H, P), R)
    S = [
        [
            jnp.where(valid[c], S[c][c], 1.0)
            if c == d
            else jnp.where(valid[c] & valid[d], S[c][d], 0.0)
            for d in range(m)
        ]
        for c in range(m)
    ]
    PHt = [[jnp.where(valid[c], PHt[i][c], 0.0) for c in range(m)] for i in range(n)]
    S, PHt = sm.materialize((S, PHt))
    L, inv_diag, repaired = sm.chol(S, floor)
    L, inv_diag, e = sm.materialize((L, inv_diag, e))
    # Row i of K = P H' S^-1 solves S k_i = (P H')_i (S symmetric).
    K = [sm.chol_solve_vec_t(L, sm.chol_solve_vec(L, row, inv_diag), inv_diag) for row in PHt]
    K = sm.materialize(K)
    v = sm.chol_solve_vec(L, e, inv_diag)
    nis = sm.dot(v, v)
    logdet = sm.chol_logdet(L)
    num_obs = sum(vv.astype(jnp.int32) for vv in valid)
    loglik = -0.5 * (nis + logdet) - (0.5 * LOG_2PI) * num_obs.astype(nis.dtype)
    x_new = sm.add(x, sm.matvec(K, e))
    IKH = sm.materialize(sm.sub(sm.eye(n), sm.matmul(K, H)))
    P_new = sm.add(sm.quad_sym(IKH, P), sm.quad_sym(K, R))
    return UpdateResult(x_new, P_new, loglik, nis, repaired, num_obs)


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
    x_pred = f(mean, u)
    P = kf_predict_cov(
        sm.from_array(F, 2), sm.from_array(jnp.asarray(cov), 2), sm.from_array(jnp.asarray(Q), 2)
    )
    return x_pred, sm.to_array(P, (), x_pred.dtype)


def ekf_update(mean, cov, y, h, R):
    """EKF measurement update for one model (eqs. 20, 21, 23-27).

    Args:
        mean: ``(n,)`` predicted mean.
        cov: ``(n, n)`` predicted covariance.
        y: ``(m,)`` measurement; NaN entries are missing channels.
        h: ``h(x) -> y_pred``.
        R: ``(m, m)`` measurement noise covariance.

    Returns:
        ``(mean, cov, loglik)`` with the Joseph-form covariance.
    """
    mean = jnp.asarray(mean)
    H = jax.jacfwd(h)(mean)
    y_pred = h(mean)
    res = kf_update(
        sm.from_array(mean, 1),
        sm.from_array(jnp.asarray(cov), 2),
        sm.from_array(jnp.asarray(y, mean.dtype), 1),
        sm.from_array(y_pred, 1),
        sm.from_array(H, 2),
        sm.from_array(jnp.asarray(R), 2),
        _floor_for(mean.dtype),
    )
    return (sm.to_array(res.mean, (), mean.dtype), sm.to_array(res.cov, (), mean.dtype), res.loglik)
