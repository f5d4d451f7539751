"""Reverse mode of the engine's hand-written adjoints against textbook references.

The measurement update (:func:`uimm_jax.engine.kalman.kf_update`), the mixing
(:func:`uimm_jax.engine.imm.mix`), the predicted covariance and the time loop's
``log_normalize`` and :func:`uimm_jax.engine._block.mirror_lower` carry
their own ``custom_vjp``; here their
gradients are compared with JAX's reverse mode through plain formulas: the Kalman update
written with ``jnp.linalg.solve`` and ``slogdet`` (Joseph form, missing channels and gate
as the engine documents them), the mixing as its own forward formulas, and the mirror
as ``tril`` plus a transpose.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uimm_jax.engine import _block as bk
from uimm_jax.engine import imm, kalman
from uimm_jax.engine.dynamics import LinearCache, MatrixBankDynamics

FLOOR = float(np.finfo(np.float64).tiny) ** 0.5


def _spd(rng, k, batch, scale=1.0, ridge=0.5):
    a = rng.normal(size=(k, k) + batch)
    s = np.einsum("ij...,kj...->ik...", a, a) * scale
    return s + ridge * scale * np.eye(k).reshape((k, k) + (1,) * len(batch))


def _reference_one(x, P, y, y_pred, H, R, gate):
    """One filter's update in textbook form (batch-first, single filter)."""
    m = y_pred.shape[0]
    valid = jnp.isfinite(y)
    vv = valid[:, None] & valid[None, :]
    e = jnp.where(valid, y - y_pred, 0.0)
    Hv = jnp.where(valid[:, None], H, 0.0)
    S = jnp.where(vv, Hv @ P @ Hv.T + R, jnp.eye(m))
    a = jnp.linalg.solve(S, e)
    nis = e @ a
    _, logdet = jnp.linalg.slogdet(S)
    loglik = -0.5 * (nis + logdet) - 0.5 * np.log(2 * np.pi) * jnp.sum(valid)
    K = jnp.linalg.solve(S, Hv @ P).T
    if gate is not None:
        keep = jax.lax.stop_gradient(nis) < gate
        K = jnp.where(keep, K, 0.0)
        loglik = jnp.where(keep, loglik, 0.0)
    A = jnp.eye(P.shape[0]) - K @ Hv
    Rv = jnp.where(vv, R, 0.0)
    return x + K @ e, A @ P @ A.T + K @ Rv @ K.T, loglik, nis, e**2 / jnp.diagonal(S)


def _batch_first(a, nb):
    return jnp.moveaxis(a, tuple(range(a.ndim - nb, a.ndim)), tuple(range(nb)))


def _reference(x, P, y, y_pred, H, R, gate):
    """The textbook update vmapped over the trailing batch axes (broadcast first)."""
    batch = x.shape[1:]
    nb = len(batch)
    bc = lambda a, lead: jnp.broadcast_to(a, a.shape[:lead] + batch)  # noqa: E731
    args = [
        bc(x, 1),
        bc(P, 2),
        bc(y, 1),
        bc(y_pred, 1),
        bc(jnp.asarray(H).reshape(H.shape + (1,) * (nb + 2 - H.ndim)), 2),
        bc(R, 2),
    ]
    flat = [_batch_first(a, nb).reshape((-1,) + a.shape[: a.ndim - nb]) for a in args]
    outs = jax.vmap(lambda *a: _reference_one(*a, gate))(*flat)
    return [
        jnp.moveaxis(o.reshape(batch + o.shape[1:]), tuple(range(nb)), tuple(range(-nb, 0)))
        for o in outs
    ]


def _problem(seed, n=3, m=3, batch=(4, 2)):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n,) + batch)
    P = _spd(rng, n, batch)
    y = rng.normal(size=(m, 1, batch[1]))
    y[1, 0, 1] = np.nan  # one missing channel in one run
    y_pred = rng.normal(size=(m,) + batch)
    R = _spd(rng, m, ())[..., None, None]
    shapes = [(n,) + batch, (n, n) + batch, batch, batch, (m,) + batch]
    weights = [rng.normal(size=s) for s in shapes]
    return rng, x, P, y, y_pred, R, weights


def _sym(g):
    return 0.5 * (g + np.swapaxes(g, 0, 1))


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("h_kind", ["identity", "constant", "traced"])
@pytest.mark.parametrize("gate", [None, 0.5])
def test_update_gradient_equals_the_textbook_update(seed, h_kind, gate):
    rng, x, P, y, y_pred, R, weights = _problem(seed)
    n, m = x.shape[0], y_pred.shape[0]
    H = {
        "identity": np.eye(m, n),
        "constant": rng.normal(size=(m, n)),
        "traced": jnp.asarray(rng.normal(size=(m, n) + x.shape[1:])),
    }[h_kind]
    accept = None if gate is None else (lambda nis: nis < gate)

    def total(outs):
        return sum(jnp.sum(w * jnp.nan_to_num(o)) for w, o in zip(weights, outs, strict=True))

    def engine(x, P, y, y_pred, H, R):
        r = kalman.kf_update(x, P, y, y_pred, H, R, FLOOR, accept)
        return total((r.mean, r.cov, r.loglik, r.nis, r.nis_channels))

    def textbook(x, P, y, y_pred, H, R):
        return total(_reference(x, P, y, y_pred, H, R, gate))

    traced = isinstance(H, jax.Array)
    argnums = (0, 1, 2, 3, 4, 5) if traced else (0, 1, 2, 3, 5)
    args = (x, P, y, y_pred, H, R)
    np.testing.assert_allclose(engine(*args), textbook(*args), rtol=1e-12)
    g_engine = jax.grad(engine, argnums)(*args)
    g_ref = jax.grad(textbook, argnums)(*args)
    if gate is not None:  # the gate rejects some filters and keeps others
        keep = np.asarray(kalman.kf_update(*args, FLOOR, accept).accepted)
        assert keep.any() and not keep.all()
    for i, a, b in zip(argnums, g_engine, g_ref, strict=True):
        a, b = np.asarray(a), np.asarray(b)
        if i in (1, 5):  # a covariance: only its symmetric part is a derivative
            a, b = _sym(a), _sym(b)
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-11 * np.max(np.abs(b)))


def test_covariance_gradient_is_accurate_when_the_update_removes_nearly_all_variance():
    # A precise sensor against a vague prior (the actuator's first steps): P - W W'
    # cancels there, and so would reverse mode through it (errors ~eps on a derivative
    # of size (r / p)^2 ~ 1e-26).  The adjoint differentiates the Joseph form, including
    # its (first-order zero) gain term: 1 - K carries a relative rounding error of
    # ~eps p / r = 1e-3 here, and that term cancels it to first order (without it the
    # relative error of dP_new/dp was 6e-4; with it 5e-7, as reverse mode through the
    # Joseph branch gave before the adjoint was written).
    p = jnp.asarray(np.geomspace(1e-3, 10.0, 7)[None, None, :])
    r = jnp.full((1, 1, 7), 1e-12)

    def posterior_variance(p, r):
        res = kalman.kf_update(
            jnp.zeros((1, 7)), p, jnp.full((1, 7), 0.5), jnp.zeros((1, 7)), np.eye(1), r, FLOOR
        )
        return jnp.sum(res.cov)

    gp, gr = jax.grad(posterior_variance, (0, 1))(p, r)
    np.testing.assert_allclose(np.asarray(gp), (r / (p + r)) ** 2, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(gr), (p / (p + r)) ** 2, rtol=1e-12)


@pytest.mark.parametrize("per_run", [False, True])
def test_mixing_gradient_equals_reverse_mode_through_its_formulas(per_run):
    # An impossible model (log mu = -inf), a model no other can reach in one run
    # (c_j = 0: it keeps its own estimate) and transitions shared or per run.
    rng = np.random.default_rng(3)
    n, M, B = 3, 4, 2
    mean = rng.normal(size=(n, M, B))
    cov = _spd(rng, n, (M, B))
    log_mu = np.log(rng.dirichlet(np.ones(M), size=B).T)
    log_mu[2, 1] = -np.inf
    log_mu[3] = -np.inf
    P = rng.dirichlet(np.ones(M), size=M)
    P[:, 3] = 0.0
    P[3] = [0.0, 0.0, 0.0, 1.0]  # model 3 is reached only from itself
    with np.errstate(divide="ignore"):
        log_t = np.log(P)
    if per_run:
        log_t = np.stack([log_t, np.log(rng.dirichlet(np.ones(M), size=M))], axis=-1)
    weights = [rng.normal(size=s) for s in [(n, M, B), (n, n, M, B), (M, B)]]

    def total(mix, *args):
        x0, P0, log_c = mix(*args)
        log_c = jnp.where(jnp.isfinite(log_c), log_c, 0.0)
        return sum(jnp.sum(w * o) for w, o in zip(weights, (x0, P0, log_c), strict=True))

    def formulas(mean, cov, log_mu, log_t):
        trans = bk.align(jnp.exp(log_t), 2, log_mu.ndim - 1)
        return imm._mix_pairwise_fwd(mean, cov, log_mu, trans)[0]

    args = (mean, cov, log_mu, log_t)
    assert not np.all(np.isfinite(np.asarray(jax.jit(imm.mix)(*args)[2])))  # c_j = 0 reached
    # compiled: op by op, the first parametrisation compiled ~150 small kernels
    g_hand = jax.jit(jax.grad(lambda *a: total(imm.mix, *a), (0, 1, 2, 3)))(*args)
    g_ref = jax.jit(jax.grad(lambda *a: total(formulas, *a), (0, 1, 2, 3)))(*args)
    for a, b in zip(g_hand, g_ref, strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14 * np.max(np.abs(b)))


def test_mirror_lower_gradient_equals_that_of_tril_plus_transpose():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(4, 4, 3, 2))
    w = rng.normal(size=(4, 4, 3, 2))

    def ref(a):
        lower = np.tril(np.ones((4, 4)))[..., None, None]
        strict = np.tril(np.ones((4, 4)), -1)[..., None, None]
        return a * lower + jnp.swapaxes(a * strict, 0, 1)

    np.testing.assert_array_equal(np.asarray(bk.mirror_lower(a)), np.asarray(ref(a)))
    g = jax.grad(lambda a: jnp.sum(w * bk.mirror_lower(a)))(a)
    g_ref = jax.grad(lambda a: jnp.sum(w * ref(a)))(a)
    np.testing.assert_allclose(np.asarray(g), np.asarray(g_ref), rtol=1e-15)


@pytest.mark.parametrize("perturbed_F", [False, True])
def test_predicted_covariance_gradient_equals_reverse_mode_through_kf_predict_cov(perturbed_F):
    # F shared by the bank (a linear plant's Ad, no tangent) or per model with a tangent
    # (an EKF's Jacobian), Q broadcast over the batch.
    rng = np.random.default_rng(5)
    n, M, B = 3, 4, 2
    F = rng.normal(size=(n, n, M, B))
    P = _spd(rng, n, (M, B))
    Q = _spd(rng, n, ())[..., None, None]
    w = rng.normal(size=(n, n, M, B))

    def total(fn, F, P, Q):
        return jnp.sum(w * fn(F, P, Q))

    argnums = (0, 1, 2) if perturbed_F else (1, 2)
    g = jax.grad(lambda *a: total(kalman._predict_cov, *a), argnums)(F, P, Q)
    g_ref = jax.grad(lambda *a: total(kalman.kf_predict_cov, *a), argnums)(F, P, Q)
    for a, b in zip(g, g_ref, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-14)


def test_log_normalize_gradient_equals_reverse_mode_through_its_formulas():
    # Finite weights, an impossible model (-inf) and a run where every model is (the
    # weights then pass through unchanged, the normaliser is -inf).
    rng = np.random.default_rng(6)
    log_w = rng.normal(size=(4, 3)) * 30.0
    log_w[1, 0] = -np.inf
    log_w[:, 2] = -np.inf
    w_out, w_lse = rng.normal(size=(4, 3)), rng.normal(size=(3,))

    def total(fn, log_w):
        out, lse = fn(log_w)
        out = jnp.where(jnp.isfinite(out), out, 0.0)
        lse = jnp.where(jnp.isfinite(lse), lse, 0.0)
        return jnp.sum(w_out * out) + jnp.sum(w_lse * lse)

    g = np.asarray(jax.jit(jax.grad(lambda a: total(imm._log_normalize_vjp, a)))(log_w))
    g_ref = np.asarray(jax.jit(jax.grad(lambda a: total(imm.log_normalize, a)))(log_w))
    # Where every weight is -inf, reverse mode through log(0) gives NaN; the hand-written
    # one passes the (here zero) output cotangent through.
    assert np.all(np.isfinite(g)) and np.all(np.isnan(g_ref[:, 2]))
    np.testing.assert_array_equal(g[:, 2], 0.0)
    np.testing.assert_allclose(g[:, :2], g_ref[:, :2], rtol=1e-12, atol=1e-14)


def test_imm_gradient_with_a_gate_and_masked_models_matches_central_differences():
    # The gate's predicate reads the active-model mask (a traced array) inside the
    # update's custom_vjp: it is passed as an argument, not closed over (a closure leaks
    # the tracer under lax.scan).  Two outliers are rejected by the gate.
    rng = np.random.default_rng(5)
    n, M, N = 2, 3, 40
    A = np.stack([np.array([[1.0, 0.1], [0.0, a]]) for a in (0.9, 0.7, 0.5)], axis=-1)
    cache = LinearCache(jnp.asarray(A), jnp.zeros((n, 1, M)), None, None)
    dyn = MatrixBankDynamics(const_C=np.array([[1.0, 0.0]]), const_d=np.zeros(1))
    x, ys = np.array([1.0, 0.5]), []
    for _ in range(N):
        x = A[..., 0] @ x + 0.05 * rng.normal(size=n)
        ys.append([x[0] + 0.1 * rng.normal()])
    ys = np.array(ys)
    ys[[10, 25], 0] += 50.0  # outliers, ~500 sigma
    active = jnp.asarray([True, True, False])
    state0 = imm.IMMState(
        jnp.zeros((n, M)),
        jnp.broadcast_to(jnp.eye(n)[..., None], (n, n, M)),
        jnp.log(jnp.ones(M) / M),
    )
    logits0 = np.log(np.array([[0.9, 0.05, 0.05], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]]))

    def run(theta):
        log_r, logits = theta[0], theta[1:].reshape(M, M)
        params = imm.IMMParams(
            jax.nn.log_softmax(logits, axis=1),
            0.0025 * jnp.eye(n),
            0.01 * jnp.exp(log_r) * jnp.eye(1),
        )

        def body(st, y):
            st, info = imm.imm_step(
                dyn, st, cache, params, jnp.zeros(1), y, active=active, gate=9.0
            )
            return st, (info.loglik_increment, info.health)

        _, (ll, health) = jax.lax.scan(body, state0, jnp.asarray(ys))
        return jnp.sum(ll), health

    theta0 = np.concatenate([[0.2], logits0.ravel()])
    health = np.asarray(jax.jit(run)(theta0)[1])
    assert np.count_nonzero(health & imm.HEALTH_GATED) == 2
    g = np.asarray(jax.jit(jax.grad(lambda t: run(t)[0]))(theta0))
    f = jax.jit(lambda t: run(t)[0])
    eps = 1e-5
    fd = np.array(
        [(f(theta0 + eps * e) - f(theta0 - eps * e)) / (2 * eps) for e in np.eye(theta0.size)]
    )
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8 * np.max(np.abs(fd)))
