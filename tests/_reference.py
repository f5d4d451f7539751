"""Plain NumPy references for the IMM engine (test-only, deliberately naive).

Everything here is written for clarity, not speed: Python loops over time and over
models, one ``np.linalg`` call per matrix.  The engine (``uimm_jax.imm_filter``) is
tested against :func:`naive_imm`; :func:`naive_imm` itself is validated against
filterpy's ``IMMEstimator``, the vectorised NumPy baseline in
``benchmarks/_baselines.py`` and the textbook :func:`kalman_filter`
(``tests/test_references.py``).

Conventions (the engine's contract, design.md section 2, paper eqs. 15-31):

* arrays carry a leading model axis: ``A (M,n,n)``, ``B (M,n,p)``, ``C (M,m,n)``,
  ``Q (M,n,n)``, ``R (M,m,m)``;
* ``x0 (M,n)``, ``P0 (M,n,n)`` are the per-model posteriors *before* step 0 and
  ``mu0 (M,)`` their mode probabilities, so step 0 starts with a mixing step;
* ``transition[i, j] = P(mode j at k+1 | mode i at k)`` (rows sum to 1);
* a NaN entry of ``measurements[k]`` is a missing channel: its rows of ``C``, ``R``
  and ``y`` are dropped; if every channel is missing the step is predict-only and
  every model's log-likelihood is 0.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["IMM_ARGS", "kalman_filter", "make_linear_problem", "naive_imm", "philox4x32"]

#: Argument names shared by every IMM reference, in order.
IMM_ARGS = (
    "A",
    "B",
    "C",
    "Q",
    "R",
    "transition",
    "mu0",
    "x0",
    "P0",
    "inputs",
    "measurements",
)


def _logsumexp(values):
    """log(sum(exp(values))) of a 1-D array, with the max-shift; -inf if all are -inf."""
    top = max(values)
    if top == -math.inf:
        return -math.inf
    return top + math.log(sum(math.exp(v - top) for v in values))


def _gaussian_logpdf(e, S):
    """log N(e; 0, S) for a 1-D innovation ``e`` (paper eq. 27, in log space)."""
    d = e.shape[0]
    sign, logdet = np.linalg.slogdet(S)
    if sign <= 0:
        raise np.linalg.LinAlgError("innovation covariance is not positive definite")
    maha = float(e @ np.linalg.solve(S, e))
    return -0.5 * (d * math.log(2.0 * math.pi) + logdet + maha)


def naive_imm(A, B, C, Q, R, transition, mu0, x0, P0, inputs, measurements):
    """Run an IMM with one linear Kalman filter per model: plain loops, float64.

    Each step k: mixing (eqs. 15-17), per-model predict with ``inputs[k]`` and Joseph
    update with ``measurements[k]`` (eqs. 18-26), log-likelihood of the innovation
    (eq. 27), mode probabilities normalised in log space (eq. 28) and the combined
    estimate (eqs. 30-31).

    A model whose predicted probability ``c_j`` is exactly 0 (a zero column of
    ``transition``) has undefined mixing weights; it keeps its own previous posterior
    (weight 1 on itself).  Its probability stays 0 so the combined outputs do not
    depend on this choice.

    Returns:
        dict with ``mode_probs (N,M)``, ``log_mode_probs (N,M)``, ``mean (N,n)``,
        ``cov (N,n,n)``, ``model_mean (N,M,n)``, ``model_cov (N,M,n,n)``,
        ``model_loglik (N,M)`` and ``marginal_loglik`` (float: the sum over k of
        ``logsumexp_j(model_loglik[k, j] + log c_j)``).
    """
    A, B, C, Q, R = (np.asarray(a, dtype=np.float64) for a in (A, B, C, Q, R))
    transition = np.asarray(transition, dtype=np.float64)
    mu = np.asarray(mu0, dtype=np.float64).copy()
    inputs = np.asarray(inputs, dtype=np.float64)
    measurements = np.asarray(measurements, dtype=np.float64)
    num_models, n = np.asarray(x0).shape
    num_steps = measurements.shape[0]

    xs = [np.array(x0[j], dtype=np.float64) for j in range(num_models)]
    Ps = [np.array(P0[j], dtype=np.float64) for j in range(num_models)]

    out_mu = np.zeros((num_steps, num_models))
    out_log_mu = np.zeros((num_steps, num_models))
    out_mean = np.zeros((num_steps, n))
    out_cov = np.zeros((num_steps, n, n))
    out_model_mean = np.zeros((num_steps, num_models, n))
    out_model_cov = np.zeros((num_steps, num_models, n, n))
    out_ll = np.zeros((num_steps, num_models))
    marginal = 0.0

    for k in range(num_steps):
        # 1. predicted mode probabilities c_j and mixing weights w_ij (eq. 15)
        c = [sum(transition[i, j] * mu[i] for i in range(num_models)) for j in range(num_models)]
        mixed_x, mixed_P = [], []
        for j in range(num_models):
            if c[j] > 0.0:
                w = [transition[i, j] * mu[i] / c[j] for i in range(num_models)]
            else:
                w = [1.0 if i == j else 0.0 for i in range(num_models)]
            # 2. mixed initial conditions (eqs. 16-17), with the spread-of-means term
            xj = np.zeros(n)
            for i in range(num_models):
                xj = xj + w[i] * xs[i]
            Pj = np.zeros((n, n))
            for i in range(num_models):
                d = xs[i] - xj
                Pj = Pj + w[i] * (Ps[i] + np.outer(d, d))
            mixed_x.append(xj)
            mixed_P.append(Pj)

        # 3. per-model Kalman predict and update
        y = measurements[k]
        observed = ~np.isnan(y)
        lls = []
        for j in range(num_models):
            x = A[j] @ mixed_x[j] + B[j] @ inputs[k]
            P = A[j] @ mixed_P[j] @ A[j].T + Q[j]
            if observed.any():
                Cj = C[j][observed, :]
                Rj = R[j][np.ix_(observed, observed)]
                e = y[observed] - Cj @ x
                S = Cj @ P @ Cj.T + Rj
                K = np.linalg.solve(S, Cj @ P).T  # = P C' S^-1 (S and P symmetric)
                x = x + K @ e
                I_KC = np.eye(n) - K @ Cj
                P = I_KC @ P @ I_KC.T + K @ Rj @ K.T
                ll = _gaussian_logpdf(e, S)  # 4. eq. 27 in log space
            else:
                ll = 0.0
            xs[j], Ps[j] = x, P
            lls.append(ll)

        # 5. mode probabilities mu_j ∝ exp(ll_j) c_j, normalised in log space (eq. 28)
        log_c = [math.log(cj) if cj > 0.0 else -math.inf for cj in c]
        log_joint = [lls[j] + log_c[j] for j in range(num_models)]
        log_norm = _logsumexp(log_joint)
        marginal += log_norm
        log_mu = [lj - log_norm for lj in log_joint]
        mu = np.array([math.exp(v) for v in log_mu])

        # 7. combined estimate (eqs. 30-31)
        mean = np.zeros(n)
        for j in range(num_models):
            mean = mean + mu[j] * xs[j]
        cov = np.zeros((n, n))
        for j in range(num_models):
            d = xs[j] - mean
            cov = cov + mu[j] * (Ps[j] + np.outer(d, d))

        out_mu[k] = mu
        out_log_mu[k] = log_mu
        out_mean[k] = mean
        out_cov[k] = cov
        for j in range(num_models):
            out_model_mean[k, j] = xs[j]
            out_model_cov[k, j] = Ps[j]
        out_ll[k] = lls

    return {
        "mode_probs": out_mu,
        "log_mode_probs": out_log_mu,
        "mean": out_mean,
        "cov": out_cov,
        "model_mean": out_model_mean,
        "model_cov": out_model_cov,
        "model_loglik": out_ll,
        "marginal_loglik": marginal,
    }


def kalman_filter(A, B, C, Q, R, x0, P0, inputs, measurements):
    """Textbook single-model Kalman filter (no NaN handling), independent of :func:`naive_imm`.

    Uses ``inv`` for the gain, the short covariance update ``P = (I - K C) P`` and
    ``log det`` via ``slogdet``: a different code path from the IMM references.
    Single-model arrays: ``A (n,n)``, ``B (n,p)``, ``C (m,n)``, ``Q (n,n)``, ``R (m,m)``.

    Returns:
        dict with ``mean (N,n)``, ``cov (N,n,n)``, ``loglik (N,)``, ``nis (N,)`` (the
        innovation's ``e' S^-1 e``), ``nis_channels (N,m)`` (each channel's
        ``e_i^2 / S_ii``) and ``marginal_loglik`` (the sum of ``loglik``).
    """
    x = np.asarray(x0, dtype=np.float64)
    P = np.asarray(P0, dtype=np.float64)
    means, covs, lls, nis, nis_ch = [], [], [], [], []
    for u, y in zip(np.asarray(inputs), np.asarray(measurements), strict=True):
        x = A @ x + B @ u
        P = A @ P @ A.T + Q
        S = C @ P @ C.T + R
        S_inv = np.linalg.inv(S)
        K = P @ C.T @ S_inv
        e = y - C @ x
        x = x + K @ e
        P = (np.eye(x.shape[0]) - K @ C) @ P
        P = 0.5 * (P + P.T)
        _, logdet = np.linalg.slogdet(2.0 * np.pi * S)
        lls.append(-0.5 * (logdet + e @ S_inv @ e))
        nis.append(e @ S_inv @ e)
        nis_ch.append(e**2 / np.diag(S))
        means.append(x)
        covs.append(P)
    lls = np.asarray(lls)
    return {
        "mean": np.asarray(means),
        "cov": np.asarray(covs),
        "loglik": lls,
        "nis": np.asarray(nis),
        "nis_channels": np.asarray(nis_ch),
        "marginal_loglik": float(lls.sum()),
    }


def _spd_matrix(rng, n, scale):
    """Random well-conditioned SPD (n,n) matrix with mean eigenvalue about ``scale``."""
    L = rng.standard_normal((n, n)) / math.sqrt(n)
    S = L @ L.T + np.eye(n)
    return scale * S / (np.trace(S) / n)


def make_linear_problem(seed, M=3, n=2, m=1, p=1, N=200, *, return_truth=False):
    """A random, well-conditioned, stable linear IMM problem with a switching truth.

    Models share a base dynamics matrix plus a model-specific perturbation, each
    rescaled to a spectral norm in [0.7, 0.9] (contractions: stable without
    transient growth); they also differ in ``B`` and in
    the process-noise scale (``Q`` spans a decade over the models), so mode
    probabilities move.  Noise levels keep the innovations O(1): every model's
    log-likelihood stays far above ``log(sys.float_info.min)`` (~ -708), so
    filterpy's linear-space likelihood clamp does not fire.

    The truth follows the Markov chain ``transition`` from a mode drawn from ``mu0``,
    starts from ``x ~ N(x0[mode], P0[mode])`` and is driven by a sine input plus a
    small random input.

    Args:
        seed: seed of ``np.random.default_rng``.
        M, n, m, p: number of models, state, measurement and input dimensions.
        N: number of time steps.
        return_truth: also return ``{"modes": (N,) int, "states": (N,n)}``.

    Returns:
        dict with exactly the keys of :data:`IMM_ARGS` (so ``naive_imm(**problem)``
        works), or ``(problem, truth)`` if ``return_truth``.
    """
    rng = np.random.default_rng(seed)
    base = rng.standard_normal((n, n))
    norms = np.linspace(0.7, 0.9, M) if M > 1 else np.array([0.9])
    A = np.stack(
        [_contraction(base + 0.3 * rng.standard_normal((n, n)), norms[j]) for j in range(M)]
    )
    B = 0.5 * rng.standard_normal((n, p)) + 0.2 * rng.standard_normal((M, n, p))
    C = np.broadcast_to(rng.standard_normal((m, n)) + np.eye(m, n), (M, m, n)).copy()
    q_scales = np.logspace(-1.5, -0.5, M) if M > 1 else np.array([0.1])
    Q = np.stack([_spd_matrix(rng, n, q_scales[j]) for j in range(M)])
    R = np.broadcast_to(_spd_matrix(rng, m, 0.2), (M, m, m)).copy()

    if M > 1:
        stay = rng.uniform(0.9, 0.97, size=M)
        off = rng.uniform(0.5, 1.5, size=(M, M))
        np.fill_diagonal(off, 0.0)
        transition = off / off.sum(axis=1, keepdims=True) * (1.0 - stay)[:, None]
        transition[np.diag_indices(M)] = stay
    else:
        transition = np.ones((1, 1))
    mu0 = rng.dirichlet(np.full(M, 5.0))
    x0 = 0.5 * rng.standard_normal((M, n))
    P0 = np.stack([_spd_matrix(rng, n, 0.5) for _ in range(M)])

    t = np.arange(N)
    inputs = np.sin(2.0 * np.pi * t / 40.0)[:, None] * np.ones(p) + 0.2 * rng.standard_normal(
        (N, p)
    )

    modes = np.zeros(N, dtype=int)
    states = np.zeros((N, n))
    measurements = np.zeros((N, m))
    mode = rng.choice(M, p=mu0)
    x = rng.multivariate_normal(x0[mode], P0[mode])
    for k in range(N):
        mode = rng.choice(M, p=transition[mode])
        x = A[mode] @ x + B[mode] @ inputs[k] + rng.multivariate_normal(np.zeros(n), Q[mode])
        measurements[k] = C[mode] @ x + rng.multivariate_normal(np.zeros(m), R[mode])
        modes[k] = mode
        states[k] = x

    problem = {
        "A": A,
        "B": B,
        "C": C,
        "Q": Q,
        "R": R,
        "transition": transition,
        "mu0": mu0,
        "x0": x0,
        "P0": P0,
        "inputs": inputs,
        "measurements": measurements,
    }
    if return_truth:
        return problem, {"modes": modes, "states": states}
    return problem


def _contraction(G, norm):
    """Rescale ``G`` to spectral norm ``norm`` (< 1: stable, and no transient growth)."""
    return norm * G / np.linalg.norm(G, 2)


def philox4x32(key, counter, rounds=10):
    """Philox4x32 (Salmon et al. 2011, Random123) in plain NumPy: 64-bit products.

    Args:
        key: ``(k0, k1)`` 32-bit words (arrays broadcast with the counter).
        counter: ``(c0, c1, c2, c3)`` 32-bit words.
        rounds: Philox rounds (10 is Random123's default).

    Returns:
        The four output words as uint32 arrays.
    """
    mask = np.uint64(0xFFFFFFFF)
    k0, k1 = (np.asarray(a, np.uint64) for a in key)
    x0, x1, x2, x3 = (np.asarray(a, np.uint64) for a in counter)
    for r in range(rounds):
        if r:  # Random123 bumps the key after every round but the last
            k0, k1 = (k0 + np.uint64(0x9E3779B9)) & mask, (k1 + np.uint64(0xBB67AE85)) & mask
        p0 = x0 * np.uint64(0xD2511F53)  # < 2^64: exact
        p1 = x2 * np.uint64(0xCD9E8D57)
        x0, x1, x2, x3 = (
            (p1 >> np.uint64(32)) ^ x1 ^ k0,
            p1 & mask,
            (p0 >> np.uint64(32)) ^ x3 ^ k1,
            p0 & mask,
        )
    return tuple(np.asarray(a, np.uint32) for a in (x0, x1, x2, x3))
