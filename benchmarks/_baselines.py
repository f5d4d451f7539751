"""Baselines the JAX engine is benchmarked (and tested) against.

* :func:`vectorised_numpy_imm` -- the "vectorised NumPy IMM": batched ``einsum`` and
  ``np.linalg`` over the model axis, Python loop over time.
* :func:`filterpy_imm` -- filterpy's ``IMMEstimator`` with one ``KalmanFilter`` per
  model: the pure-Python loop most users would write.

Both take the same arguments as the naive test reference ``naive_imm`` and follow the
same conventions (see ``tests/_reference.py``, which this module re-exports together
with ``make_linear_problem`` so benchmark scripts need one import).  Tests import this
module by putting the ``benchmarks`` folder on ``sys.path``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

_TESTS = str(Path(__file__).resolve().parents[1] / "tests")
if _TESTS not in sys.path:
    sys.path.insert(0, _TESTS)

from _reference import IMM_ARGS, make_linear_problem, naive_imm  # noqa: E402

__all__ = [
    "IMM_ARGS",
    "filterpy_imm",
    "make_linear_problem",
    "naive_imm",
    "vectorised_numpy_imm",
]


def vectorised_numpy_imm(A, B, C, Q, R, transition, mu0, x0, P0, inputs, measurements):
    """IMM vectorised over models with NumPy (time loop in Python), float64.

    Same arguments, conventions and outputs as ``naive_imm`` (mixing eqs. 15-17,
    Joseph-form KF update, log-space likelihoods eq. 27 and mode probabilities eq. 28,
    combined estimate eqs. 30-31; NaN = missing channel; a model with ``c_j = 0``
    keeps its own posterior as its mixed initial condition).  Batched
    ``np.linalg.solve`` gives the gains; a batched Cholesky of the innovation
    covariances gives the log-determinants and Mahalanobis terms.

    Returns:
        dict with ``mode_probs (N,M)``, ``log_mode_probs (N,M)``, ``mean (N,n)``,
        ``cov (N,n,n)``, ``model_mean (N,M,n)``, ``model_cov (N,M,n,n)``,
        ``model_loglik (N,M)`` and ``marginal_loglik`` (float).
    """
    A, B, C, Q, R = (np.asarray(a, dtype=np.float64) for a in (A, B, C, Q, R))
    T = np.asarray(transition, dtype=np.float64)
    mu = np.asarray(mu0, dtype=np.float64)
    x = np.array(x0, dtype=np.float64)
    P = np.array(P0, dtype=np.float64)
    inputs = np.asarray(inputs, dtype=np.float64)
    measurements = np.asarray(measurements, dtype=np.float64)
    num_steps = measurements.shape[0]
    num_models, n = x.shape
    eye_n = np.eye(n)
    eye_M = np.eye(num_models)
    AT = np.swapaxes(A, -1, -2)
    Bu = np.einsum("jnp,kp->kjn", B, inputs)  # (N, M, n): all input terms at once
    observed = ~np.isnan(measurements)
    log_2pi = np.log(2.0 * np.pi)

    out = {
        "mode_probs": np.empty((num_steps, num_models)),
        "log_mode_probs": np.empty((num_steps, num_models)),
        "mean": np.empty((num_steps, n)),
        "cov": np.empty((num_steps, n, n)),
        "model_mean": np.empty((num_steps, num_models, n)),
        "model_cov": np.empty((num_steps, num_models, n, n)),
        "model_loglik": np.empty((num_steps, num_models)),
    }
    marginal = 0.0
    with np.errstate(divide="ignore"):
        for k in range(num_steps):
            # mixing (eqs. 15-17)
            c = mu @ T
            alive = c > 0.0
            W = np.where(alive, T * mu[:, None] / np.where(alive, c, 1.0), eye_M)  # W[i, j]
            xm = W.T @ x
            d = x[:, None, :] - xm[None, :, :]  # (i, j, n)
            spread = np.einsum("ija,ijb->jab", W[:, :, None] * d, d)
            Pm = (W.T @ P.reshape(num_models, -1)).reshape(P.shape) + spread

            # predict
            xp = (A @ xm[:, :, None])[:, :, 0] + Bu[k]
            Pp = A @ Pm @ AT + Q

            # update on the observed channels
            obs = observed[k]
            num_obs = int(obs.sum())
            if num_obs == obs.size:
                Co, Ro, y = C, R, measurements[k]
            elif num_obs > 0:
                Co, Ro, y = C[:, obs, :], R[:, obs][:, :, obs], measurements[k, obs]
            if num_obs > 0:
                e = y - (Co @ xp[:, :, None])[:, :, 0]
                CP = Co @ Pp
                S = CP @ np.swapaxes(Co, -1, -2) + Ro
                L = np.linalg.cholesky(S)
                K = np.swapaxes(np.linalg.solve(S, CP), -1, -2)  # P C' S^-1
                x = xp + (K @ e[:, :, None])[:, :, 0]
                IKC = eye_n - K @ Co
                P = IKC @ Pp @ np.swapaxes(IKC, -1, -2) + K @ Ro @ np.swapaxes(K, -1, -2)
                z = np.linalg.solve(L, e[:, :, None])[:, :, 0]  # L^-1 e
                logdet = 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)
                ll = -0.5 * (num_obs * log_2pi + logdet + (z * z).sum(-1))
            else:
                x, P = xp, Pp
                ll = np.zeros(num_models)

            # mode probabilities in log space (eq. 28)
            log_joint = ll + np.log(c)
            top = log_joint.max()
            log_norm = top + np.log(np.exp(log_joint - top).sum())
            marginal += log_norm
            log_mu = log_joint - log_norm
            mu = np.exp(log_mu)

            # combined estimate (eqs. 30-31)
            mean = mu @ x
            dx = x - mean
            cov = (mu @ P.reshape(num_models, -1)).reshape(n, n) + (mu[:, None] * dx).T @ dx

            out["mode_probs"][k] = mu
            out["log_mode_probs"][k] = log_mu
            out["mean"][k] = mean
            out["cov"][k] = cov
            out["model_mean"][k] = x
            out["model_cov"][k] = P
            out["model_loglik"][k] = ll
    out["marginal_loglik"] = float(marginal)
    return out


def filterpy_imm(A, B, C, Q, R, transition, mu0, x0, P0, inputs, measurements):
    """Run filterpy's ``IMMEstimator`` with one ``KalmanFilter`` per model.

    Notes on filterpy 2.0.0 that matter here:

    * ``IMMEstimator`` needs at least two filters (``ValueError`` otherwise);
    * its ``M[i, j]`` is P(i -> j) (``cbar = mu @ M``), the same convention as
      ``transition`` here, although its docstring says the opposite;
    * it normalises ``mu`` at construction and mixes at the start of ``predict``, so
      filter ``x``/``P`` set before the first ``predict`` are the posteriors "before
      step 0", as in ``naive_imm``;
    * mode probabilities use linear-space likelihoods, and a likelihood that
      underflows to 0 is replaced by ``sys.float_info.min`` (the clamp): results only
      match the log-space references while every log-likelihood stays above
      ``log(sys.float_info.min)`` (about -708.4);
    * ``KalmanFilter.x`` defaults to a column ``(n, 1)``; here it is set 1-D ``(n,)``
      so that ``B @ u`` with ``u (p,)`` stays ``(n,)`` (with a column ``x`` that sum
      would silently broadcast to ``(n, n)``);
    * missing data is not supported (``update(None)`` reuses a stale ``S`` for the
      likelihood), so NaN measurements raise ``ValueError``.

    Returns:
        dict with ``mode_probs (N,M)``, ``mean (N,n)``, ``cov (N,n,n)`` and
        ``model_loglik (N,M)`` (each filter's ``log_likelihood`` after ``update``).
    """
    from filterpy.kalman import IMMEstimator, KalmanFilter

    A, B, C, Q, R = (np.asarray(a, dtype=np.float64) for a in (A, B, C, Q, R))
    inputs = np.asarray(inputs, dtype=np.float64)
    measurements = np.asarray(measurements, dtype=np.float64)
    if np.isnan(measurements).any():
        raise ValueError("filterpy_imm does not support missing (NaN) measurements")
    num_models, n = np.asarray(x0).shape
    m, p = C.shape[1], B.shape[2]
    num_steps = measurements.shape[0]

    filters = []
    for j in range(num_models):
        kf = KalmanFilter(dim_x=n, dim_z=m, dim_u=p)
        kf.F = A[j].copy()
        kf.B = B[j].copy()
        kf.H = C[j].copy()
        kf.Q = Q[j].copy()
        kf.R = R[j].copy()
        kf.x = np.array(x0[j], dtype=np.float64)  # 1-D on purpose, see the notes
        kf.P = np.array(P0[j], dtype=np.float64)
        filters.append(kf)
    imm = IMMEstimator(filters, np.asarray(mu0, dtype=np.float64), np.asarray(transition))

    mode_probs = np.empty((num_steps, num_models))
    mean = np.empty((num_steps, n))
    cov = np.empty((num_steps, n, n))
    model_loglik = np.empty((num_steps, num_models))
    for k in range(num_steps):
        imm.predict(u=inputs[k])
        imm.update(measurements[k])
        mode_probs[k] = imm.mu
        mean[k] = imm.x
        cov[k] = imm.P
        model_loglik[k] = [f.log_likelihood for f in filters]
    return {"mode_probs": mode_probs, "mean": mean, "cov": cov, "model_loglik": model_loglik}
