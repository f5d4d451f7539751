"""Engine acceptance tests: EKF, exact ZOH, IMM reductions, UIMM hand-over, long runs.

Every reference is computed in this file, independently of the engine:

* a NumPy (E)KF with hand-derived Jacobians -- analytic for a discrete pendulum, the
  chain rule through every RK4 stage for a continuous Van der Pol oscillator;
* ``scipy.linalg.expm`` of the augmented matrix of the actuator, written from design.md
  section 1 (not from ``hydraulic_actuator.py``);
* Markov-chain predictions of the mode probabilities, and the UIMM hand-over rule of
  ``uimm.py``'s module docstring;
* :func:`uimm_jax.imm_filter`, itself checked against filterpy in ``test_imm_api.py``.

Compilation dominates the runtime (~10 s per filter kernel on 2 cores), so the actuator
tests share one short variant of ``paper_sim1_tuned`` (20 s, events at 2 s and 4 s),
one chunk length and ``with_cov=True``; the diagnoser is cached by the runner, so the
variants with other decision parameters reuse the same compiled chunk.
"""

import functools
import itertools
import sys
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

import uimm_jax
from uimm_jax.engine import bank, imm, kalman
from uimm_jax.engine.dynamics import NonlinearDynamics
from uimm_jax.engine.uimm import DiagState, build_diagnoser
from uimm_jax.plants.base import LinearPlant, NonlinearPlant
from uimm_jax.plants.dynamics import make_dynamics
from uimm_jax.plants.hydraulic_actuator import EXTRA_FAULTS, HYDRAULIC_ACTUATOR, PAPER_FAULTS
from uimm_jax.scenario.parse import parse_scenario
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.studies import run

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _engine_helpers import count_backend_compiles  # noqa: E402
from _reference import make_linear_problem  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
SIM1_TUNED = REPO / "scenarios" / "paper_sim1_tuned.toml"
LOG_2PI = np.log(2.0 * np.pi)

# The short variant of paper_sim1_tuned shared by the actuator tests.
SHORT_DURATION = 20.0  # s: 2e5 samples at dt = 1e-4 s
SHORT_EVENT_TIMES = (2.0, 4.0)  # valve wear, then leakage
CHUNK = 50_000  # divides 2e5: one compiled chunk for every actuator run
NEVER = 2**31 - 1  # a hold (int32) that no run reaches


# ---------------------------------------------------------------------------
# helpers


def numpy_ekf(f, f_jac, h, h_jac, Q, R, x0, P0, inputs, measurements):
    """Textbook EKF in NumPy: predict with ``inputs[k]``, then update with ``measurements[k]``.

    ``f_jac`` is evaluated at the posterior mean, ``h_jac`` at the prediction; NaN
    channels are dropped; Joseph-form covariance; ``log N(e; 0, S)`` per step.
    """
    x = np.array(x0, dtype=np.float64)
    P = np.array(P0, dtype=np.float64)
    n = x.shape[0]
    out = {"mean": [], "cov": [], "loglik": []}
    for u, y in zip(inputs, measurements, strict=True):
        F = f_jac(x, u)
        x = f(x, u)
        P = F @ P @ F.T + Q
        obs = np.isfinite(y)
        ll = 0.0
        if obs.any():
            H = h_jac(x)[obs]
            Ro = R[np.ix_(obs, obs)]
            e = y[obs] - h(x)[obs]
            S = H @ P @ H.T + Ro
            K = np.linalg.solve(S, H @ P).T
            x = x + K @ e
            IKH = np.eye(n) - K @ H
            P = IKH @ P @ IKH.T + K @ Ro @ K.T
            _, logdet = np.linalg.slogdet(S)
            ll = -0.5 * (obs.sum() * LOG_2PI + logdet + e @ np.linalg.solve(S, e))
        out["mean"].append(x)
        out["cov"].append(P)
        out["loglik"].append(ll)
    return {k: np.array(v) for k, v in out.items()}


def linear_ekf(A, B, C, Q, R, x0, P0, inputs, measurements):
    return numpy_ekf(
        lambda x, u: A @ x + B @ u,
        lambda x, u: A,
        lambda x: C @ x,
        lambda x: C,
        Q,
        R,
        x0,
        P0,
        inputs,
        measurements,
    )


def assert_ekf_equal(mean, cov, loglik, ref, rtol=1e-10):
    np.testing.assert_allclose(mean, ref["mean"], rtol=rtol, atol=1e-12)
    np.testing.assert_allclose(cov, ref["cov"], rtol=rtol, atol=1e-14)
    np.testing.assert_allclose(loglik, ref["loglik"], rtol=rtol, atol=1e-10)


def assert_symmetric_psd(cov, what):
    """``cov (..., n, n)``: symmetric and PSD relative to its own scales.

    The actuator's variances span ~14 decades, so both checks are made on the
    correlation matrix ``D^-1/2 P D^-1/2``.
    """
    d = np.sqrt(np.einsum("...ii->...i", cov))
    assert np.all(d > 0.0), what
    corr = cov / (d[..., :, None] * d[..., None, :])
    np.testing.assert_allclose(corr, np.swapaxes(corr, -1, -2), rtol=0, atol=1e-12, err_msg=what)
    eig = np.linalg.eigvalsh(0.5 * (corr + np.swapaxes(corr, -1, -2)))
    assert eig.min() > -1e-9, f"{what}: smallest correlation eigenvalue {eig.min():.3g}"


# ---------------------------------------------------------------------------
# test plants (users' own models, as a user would write them)

PEND_DT = 0.05


def pendulum_f(x, u, p):
    """Explicit-Euler damped pendulum: a discrete map with an analytic Jacobian."""
    return jnp.stack(
        [
            x[0] + PEND_DT * x[1],
            x[1] + PEND_DT * (-(p["g"] / p["l"]) * jnp.sin(x[0]) - p["b"] * x[1] + u[0]),
        ]
    )


def pendulum_h(x, p):
    """Position of the bob (non-linear in the angle)."""
    return jnp.stack([p["l"] * jnp.sin(x[0]), -p["l"] * jnp.cos(x[0])])


PENDULUM = NonlinearPlant(
    name="test_pendulum",
    state_names=("angle", "rate"),
    input_names=("torque",),
    output_names=("bob_x", "bob_y"),
    param_names=("g", "l", "b"),
    nominal_values=(9.81, 1.0, 0.3),
    time="discrete",
    f=pendulum_f,
    h=pendulum_h,
)


def pendulum_numpy(theta):
    g, l, b = theta
    dt = PEND_DT

    def f(x, u):
        return np.array([x[0] + dt * x[1], x[1] + dt * (-(g / l) * np.sin(x[0]) - b * x[1] + u[0])])

    def f_jac(x, u):
        return np.array([[1.0, dt], [-dt * (g / l) * np.cos(x[0]), 1.0 - dt * b]])

    def h(x):
        return np.array([l * np.sin(x[0]), -l * np.cos(x[0])])

    def h_jac(x):
        return np.array([[l * np.cos(x[0]), 0.0], [l * np.sin(x[0]), 0.0]])

    return f, f_jac, h, h_jac


VDP_DT = 0.05
VDP_SUBSTEPS = 5


def vdp_f(x, u, p):
    """Van der Pol vector field (continuous time)."""
    return jnp.stack([x[1], p["mu"] * (1.0 - x[0] ** 2) * x[1] - x[0] + u[0]])


def vdp_h(x, p):
    return jnp.stack([x[0], 0.5 * x[0] * x[1]])


VAN_DER_POL = NonlinearPlant(
    name="test_van_der_pol",
    state_names=("position", "velocity"),
    input_names=("force",),
    output_names=("position", "half_power"),
    param_names=("mu",),
    nominal_values=(1.5,),
    time="continuous",
    f=vdp_f,
    h=vdp_h,
    substeps=VDP_SUBSTEPS,
)


def vdp_numpy(theta, substeps=VDP_SUBSTEPS):
    """RK4 map of the Van der Pol field and its Jacobian by the chain rule, by hand."""
    (mu,) = theta
    eye = np.eye(2)

    def rhs(x, u):
        return np.array([x[1], mu * (1.0 - x[0] ** 2) * x[1] - x[0] + u[0]])

    def rhs_jac(x):
        return np.array([[0.0, 1.0], [-2.0 * mu * x[0] * x[1] - 1.0, mu * (1.0 - x[0] ** 2)]])

    def rk4_with_jac(x, u):
        h = VDP_DT / substeps
        J = eye
        for _ in range(substeps):
            k1, J1 = rhs(x, u), rhs_jac(x)
            x2 = x + 0.5 * h * k1
            k2, J2 = rhs(x2, u), rhs_jac(x2) @ (eye + 0.5 * h * J1)
            x3 = x + 0.5 * h * k2
            k3, J3 = rhs(x3, u), rhs_jac(x3) @ (eye + 0.5 * h * J2)
            x4 = x + h * k3
            k4, J4 = rhs(x4, u), rhs_jac(x4) @ (eye + h * J3)
            x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            J = (eye + (h / 6.0) * (J1 + 2.0 * J2 + 2.0 * J3 + J4)) @ J
        return x, J

    def h(x):
        return np.array([x[0], 0.5 * x[0] * x[1]])

    def h_jac(x):
        return np.array([[1.0, 0.0], [0.5 * x[1], 0.5 * x[0]]])

    return (lambda x, u: rk4_with_jac(x, u)[0]), (lambda x, u: rk4_with_jac(x, u)[1]), h, h_jac


def nonlinear_problem(name, N=100, seed=0):
    """Plant, its NumPy model, noise and a noisy truth run (truth by the NumPy map)."""
    rng = np.random.default_rng(seed)
    if name == "pendulum":
        plant, model = PENDULUM, pendulum_numpy(PENDULUM.theta())
        Q, R = np.diag([1e-5, 1e-3]), 0.05**2 * np.eye(2)
        x_true, x0, P0 = np.array([1.3, 0.0]), np.array([0.9, 0.3]), np.diag([0.3, 0.5])
        inputs = 0.5 * np.sin(np.arange(N) * 0.2)[:, None]
    else:
        plant, model = VAN_DER_POL, vdp_numpy(VAN_DER_POL.theta())
        Q, R = 1e-4 * np.eye(2), 0.05**2 * np.eye(2)
        x_true, x0, P0 = np.array([2.0, 0.0]), np.array([1.5, 0.5]), 0.5 * np.eye(2)
        inputs = 0.3 * np.cos(np.arange(N) * 0.1)[:, None]
    f, _, h, _ = model
    ys, xs = [], []
    for u in inputs:
        x_true = f(x_true, u) + rng.multivariate_normal(np.zeros(2), Q)
        xs.append(x_true)
        ys.append(h(x_true) + rng.multivariate_normal(np.zeros(2), R))
    ys = np.array(ys)
    ys[[10, 11], 1] = np.nan  # a missing channel
    ys[40] = np.nan  # a missing sample
    return SimpleNamespace(
        plant=plant, model=model, Q=Q, R=R, x0=x0, P0=P0, inputs=inputs, y=ys, x=np.array(xs)
    )


@functools.partial(jax.jit, static_argnames=("dyn",))
def run_bank_imm(dyn, cache, params, state, inputs, measurements):
    """``imm_step`` under ``lax.scan`` (one run, M models): the engine's own batch kernel."""

    def body(st, uy):
        u, y = uy
        st, info = imm.imm_step(dyn, st, cache, params, u, y)
        return st, (info.log_mode_probs, info.mean, info.cov, info.model_loglik, st.mean, st.cov)

    return jax.lax.scan(body, state, (inputs, measurements))[1]


def imm_on_plant(prob, transition, mu0):
    """IMM of ``len(mu0)`` identical copies of ``prob.plant`` (engine's NonlinearDynamics)."""
    M = len(mu0)
    dyn = NonlinearDynamics(prob.plant, VDP_DT if prob.plant is VAN_DER_POL else PEND_DT)
    theta = jnp.asarray(np.repeat(prob.plant.theta()[:, None], M, axis=1))
    with np.errstate(divide="ignore"):
        params = imm.IMMParams(
            jnp.asarray(np.log(transition)), jnp.asarray(prob.Q), jnp.asarray(prob.R)
        )
    state = imm.IMMState(
        jnp.asarray(np.repeat(prob.x0[:, None], M, axis=1)),
        jnp.asarray(np.repeat(prob.P0[:, :, None], M, axis=2)),
        jnp.log(jnp.asarray(mu0)),
    )
    out = run_bank_imm(
        dyn, dyn.prepare(theta), params, state, jnp.asarray(prob.inputs), jnp.asarray(prob.y)
    )
    log_mu, mean, cov, model_ll, model_mean, model_cov = (np.asarray(a) for a in out)
    return SimpleNamespace(
        mode_probs=np.exp(log_mu),
        mean=mean,
        cov=cov,
        model_loglik=model_ll,
        model_mean=np.moveaxis(model_mean, -1, 1),  # (N, M, n)
        model_cov=np.moveaxis(model_cov, -1, 1),  # (N, M, n, n)
    )


# ---------------------------------------------------------------------------
# EKF on linear models


@jax.jit
def ekf_linear_step(A, B, C, Q, R, x, P, u, y):
    x, P = kalman.ekf_predict(x, P, u, lambda xx, uu: A @ xx + B @ uu, Q)
    return kalman.ekf_update(x, P, y, lambda xx: C @ xx, R)


def linear_problem_with_gaps(seed, M):
    problem = make_linear_problem(seed, M=M, n=3, m=2, p=1, N=60)
    y = problem["measurements"].copy()
    y[[5, 6, 30], 1] = np.nan
    y[[12, 45]] = np.nan
    problem["measurements"] = y
    return problem


@pytest.mark.parametrize("seed", [0, 42, 99])
def test_ekf_on_a_linear_model_equals_the_kalman_filter(seed):
    p = linear_problem_with_gaps(seed, M=1)
    A, B, C, Q, R, x0, P0 = (p[k][0] for k in ("A", "B", "C", "Q", "R", "x0", "P0"))
    ref = linear_ekf(A, B, C, Q, R, x0, P0, p["inputs"], p["measurements"])
    x, P = jnp.asarray(x0), jnp.asarray(P0)
    means, covs, lls = [], [], []
    for u, y in zip(p["inputs"], p["measurements"], strict=True):
        x, P, ll = ekf_linear_step(A, B, C, Q, R, x, P, u, y)
        means.append(np.asarray(x))
        covs.append(np.asarray(P))
        lls.append(float(ll))
    assert_ekf_equal(np.array(means), np.array(covs), np.array(lls), ref)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_update_covariance_equals_the_joseph_form_and_is_exactly_symmetric(seed):
    # On a regular update the engine computes P - W W' (W = P H' L^-T); algebraically that
    # is the Joseph form, computed here with NumPy.
    rng = np.random.default_rng(seed)
    n, m = 4, 3
    G = rng.standard_normal((n, n))
    P = G @ G.T + 0.1 * np.eye(n)
    H = rng.standard_normal((m, n))
    F = rng.standard_normal((m, m))
    R = F @ F.T + 0.5 * np.eye(m)
    x, y = rng.standard_normal(n), rng.standard_normal(m)
    mean, cov, _ = kalman.ekf_update(x, P, y, lambda xx: jnp.asarray(H) @ xx, R)
    cov = np.asarray(cov)
    K = np.linalg.solve(H @ P @ H.T + R, H @ P).T
    IKH = np.eye(n) - K @ H
    np.testing.assert_allclose(cov, IKH @ P @ IKH.T + K @ R @ K.T, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(mean, x + K @ (y - H @ x), rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(cov, cov.T)


def test_update_with_a_singular_innovation_covariance_falls_back_to_joseph():
    # One state seen by two identical noise-free sensors: S is singular and a pivot is
    # floored, so P - W W' is not the covariance of the gain actually used, and it comes
    # out as +-rounding noise around 0 -- negative for some P.  The Joseph form (used when
    # a pivot is repaired) gives (1 - K H)^2 P >= 0 exactly.
    p = np.linspace(0.1, 7.3, 97)[None, None, :]  # 97 one-state filters, (1, 1, 97)
    H = np.array([[1.0], [1.0]])
    res = kalman.kf_update(
        jnp.zeros((1, 97)),
        jnp.asarray(p),
        jnp.full((2, 97), 0.5),
        jnp.zeros((2, 97)),
        H,
        jnp.zeros((2, 2, 1)),
        float(np.finfo(np.float64).tiny) ** 0.5,
    )
    assert bool(np.all(res.repaired))
    cov = np.asarray(res.cov)[0, 0]
    assert np.all(cov >= 0.0)
    assert np.all(cov <= 1e-9 * p[0, 0])


def test_update_keeps_relative_accuracy_when_a_precise_sensor_meets_a_vague_prior():
    # The actuator's first step: prior variance ~0.1, sensor variance 1e-12.  P - W W'
    # would leave 1e-12 as the difference of two numbers of size 0.1 (1.5e-3 relative
    # error, measured); the engine then switches to the Joseph form, accurate to rounding.
    p = np.geomspace(1e-3, 10.0, 41)[None, None, :]
    r = 1e-12
    res = kalman.kf_update(
        jnp.zeros((1, 41)),
        jnp.asarray(p),
        jnp.full((1, 41), 0.5),
        jnp.zeros((1, 41)),
        np.eye(1),
        jnp.full((1, 1, 1), r),
        float(np.finfo(np.float64).tiny) ** 0.5,
    )
    assert not np.any(res.repaired)
    np.testing.assert_allclose(np.asarray(res.cov)[0, 0], p[0, 0] * r / (p[0, 0] + r), rtol=1e-12)


def matrix_plant(n, p, m):
    """A discrete-time LinearPlant whose parameters are the entries of A, B and C."""
    names = (
        [f"a{i}{j}" for i in range(n) for j in range(n)]
        + [f"b{i}{k}" for i in range(n) for k in range(p)]
        + [f"c{i}{j}" for i in range(m) for j in range(n)]
    )

    def matrices(q):
        A = jnp.stack([jnp.stack([q[f"a{i}{j}"] for j in range(n)]) for i in range(n)])
        B = jnp.stack([jnp.stack([q[f"b{i}{k}"] for k in range(p)]) for i in range(n)])
        C = jnp.stack([jnp.stack([q[f"c{i}{j}"] for j in range(n)]) for i in range(m)])
        return A, B, C, jnp.zeros((m,), A.dtype)

    return LinearPlant(
        name="test_matrix_bank",
        state_names=tuple(f"x{i}" for i in range(n)),
        input_names=tuple(f"u{k}" for k in range(p)),
        output_names=tuple(f"y{i}" for i in range(m)),
        param_names=tuple(names),
        nominal_values=(0.0,) * len(names),
        time="discrete",
        matrices=matrices,
    )


@pytest.mark.parametrize("rows", [(0, 1, 2), (3, 0, 3)])
def test_products_with_a_constant_selection_matrix_are_the_dense_products(rows):
    # A 0/1 NumPy matrix with one 1 a row is applied by slicing: the same numbers as the
    # dense product, and refused as a selection when a row has no or two ones.
    from uimm_jax.engine import _block as bk

    rng = np.random.default_rng(0)
    S = np.eye(5)[list(rows)]
    assert bk.selection(S) == rows
    assert bk.selection(S + np.eye(5)[[1, 2, 4]]) is None
    assert bk.selection(np.zeros((2, 5))) is None
    b = jnp.asarray(rng.standard_normal((5, 4, 2)))
    c = jnp.asarray(rng.standard_normal((4, 5, 2)))
    v = jnp.asarray(rng.standard_normal((5, 2)))
    np.testing.assert_array_equal(bk.mm(S, b), np.einsum("ik,kjb->ijb", S, b))
    np.testing.assert_array_equal(bk.mmt(c, S), np.einsum("ikb,jk->ijb", c, S))
    np.testing.assert_array_equal(bk.mmt(S, c), np.einsum("ik,jkb->ijb", S, c))
    np.testing.assert_array_equal(bk.mv(S, v), np.einsum("ik,kb->ib", S, v))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_cholesky_log_determinant_is_the_sum_of_log_pivots_at_any_scale(dtype):
    # The log-determinant takes one log of the product of the pivots' mantissas: it must
    # equal the sum of the (floored) pivots' logs whatever their scale, where a plain
    # product of pivots would underflow or overflow, and keep +inf / -inf for degenerate S.
    from uimm_jax.engine import _block as bk

    fi = np.finfo(dtype)
    floor = float(fi.tiny) ** 0.5
    rng = np.random.default_rng(1)
    for m in (1, 3, 6):
        a = rng.standard_normal((m, m))
        s = a @ a.T + m * np.eye(m)
        for scale in (fi.tiny**0.3, 1e-12, 1.0, 1e12, fi.max**0.3):
            sm = (s * scale).astype(dtype)
            _, logdet, repaired = bk.inv_cholesky(jnp.asarray(sm)[..., None], floor)
            assert not bool(repaired[0])
            want = 2.0 * np.sum(np.log(np.diag(np.linalg.cholesky(sm.astype(np.float64)))))
            assert logdet.dtype == dtype
            np.testing.assert_allclose(
                float(logdet[0]), want, rtol=20 * fi.eps, atol=50 * m * fi.eps
            )
    # Floored pivots enter at the floor; an infinite diagonal gives +inf, no NaN.
    _, logdet, _ = bk.inv_cholesky(jnp.zeros((3, 3, 1), dtype), floor)
    np.testing.assert_allclose(float(logdet[0]), 3 * np.log(dtype(floor)), rtol=4 * fi.eps)
    s_inf = np.diag([np.inf, 1.0, 2.0]).astype(dtype)[..., None]
    assert float(bk.inv_cholesky(jnp.asarray(s_inf), floor)[1][0]) == np.inf
    # A floor below the smallest normal number admits zero pivots: log det = -inf.
    assert float(bk.inv_cholesky(jnp.zeros((3, 3, 1), dtype), 0.0)[1][0]) == -np.inf


def test_batch_kernel_on_linear_models_equals_the_kalman_filter():
    """A bank of 3 different linear models with an identity transition: 3 independent KFs.

    Goes through the engine's batch kernel (``imm_step`` over ``LinearDynamics`` of a
    user's discrete-time plant); with ``transition = I`` the mixing is exactly the identity.
    """
    M, n, p, m = 3, 3, 1, 2
    prob = linear_problem_with_gaps(7, M=M)
    Q, R = prob["Q"][0], prob["R"][0]  # the bank shares Q and R
    thetas = np.hstack([prob[k].reshape(M, -1) for k in ("A", "B", "C")])
    dyn = make_dynamics(matrix_plant(n, p, m), 1.0, thetas)
    with np.errstate(divide="ignore"):
        params = imm.IMMParams(jnp.asarray(np.log(np.eye(M))), jnp.asarray(Q), jnp.asarray(R))
    state = imm.IMMState(
        jnp.asarray(prob["x0"].T),
        jnp.asarray(np.moveaxis(prob["P0"], 0, -1)),
        jnp.log(jnp.full(M, 1.0 / M)),
    )
    out = run_bank_imm(
        dyn,
        dyn.prepare(jnp.asarray(thetas.T)),
        params,
        state,
        jnp.asarray(prob["inputs"]),
        jnp.asarray(prob["measurements"]),
    )
    _, _, _, model_ll, model_mean, model_cov = (np.asarray(a) for a in out)
    for j in range(M):
        A, B, C, x0, P0 = (prob[k][j] for k in ("A", "B", "C", "x0", "P0"))
        ref = linear_ekf(A, B, C, Q, R, x0, P0, prob["inputs"], prob["measurements"])
        assert_ekf_equal(model_mean[..., j], model_cov[..., j], model_ll[:, j], ref)


# ---------------------------------------------------------------------------
# EKF on non-linear models, against hand-derived Jacobians


@jax.jit
def ekf_pendulum_step(theta, Q, R, x, P, u, y):
    p = PENDULUM.params(theta)
    x, P = kalman.ekf_predict(x, P, u, lambda xx, uu: pendulum_f(xx, uu, p), Q)
    return kalman.ekf_update(x, P, y, lambda xx: pendulum_h(xx, p), R)


def test_ekf_on_a_nonlinear_discrete_model_matches_hand_derived_jacobians():
    prob = nonlinear_problem("pendulum")
    ref = numpy_ekf(*prob.model, prob.Q, prob.R, prob.x0, prob.P0, prob.inputs, prob.y)
    # the run is non-linear: the angle sweeps through more than a radian
    assert np.ptp(ref["mean"][:, 0]) > 1.0
    theta = jnp.asarray(PENDULUM.theta())
    x, P = jnp.asarray(prob.x0), jnp.asarray(prob.P0)
    means, covs, lls = [], [], []
    for u, y in zip(prob.inputs, prob.y, strict=True):
        x, P, ll = ekf_pendulum_step(theta, prob.Q, prob.R, x, P, u, y)
        means.append(np.asarray(x))
        covs.append(np.asarray(P))
        lls.append(float(ll))
    assert_ekf_equal(np.array(means), np.array(covs), np.array(lls), ref)


@pytest.mark.parametrize("name", ["pendulum", "van_der_pol"])
def test_one_model_imm_equals_the_hand_derived_ekf(name):
    """A one-model IMM over the engine's NonlinearDynamics (discrete map / RK4 substeps)."""
    prob = nonlinear_problem(name)
    ref = numpy_ekf(*prob.model, prob.Q, prob.R, prob.x0, prob.P0, prob.inputs, prob.y)
    out = imm_on_plant(prob, np.ones((1, 1)), np.ones(1))
    np.testing.assert_allclose(out.mode_probs, 1.0, rtol=0, atol=1e-14)
    assert_ekf_equal(out.mean, out.cov, out.model_loglik[:, 0], ref)


def test_identical_models_keep_the_markov_predicted_mode_probabilities():
    prob = nonlinear_problem("pendulum", seed=1)
    transition = np.array([[0.9, 0.06, 0.04], [0.1, 0.8, 0.1], [0.2, 0.2, 0.6]])
    mu0 = np.array([0.5, 0.3, 0.2])
    ref = numpy_ekf(*prob.model, prob.Q, prob.R, prob.x0, prob.P0, prob.inputs, prob.y)
    out = imm_on_plant(prob, transition, mu0)
    previous = np.vstack([mu0[None], out.mode_probs[:-1]])
    np.testing.assert_allclose(out.mode_probs, previous @ transition, rtol=1e-12, atol=1e-15)
    N = prob.y.shape[0]
    np.testing.assert_allclose(
        out.mode_probs[-1], mu0 @ np.linalg.matrix_power(transition, N), rtol=1e-10
    )
    assert_ekf_equal(out.mean, out.cov, out.model_loglik[:, 0], ref)
    for j in range(3):
        np.testing.assert_allclose(out.model_mean[:, j], ref["mean"], rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(out.model_cov[:, j], ref["cov"], rtol=1e-10, atol=1e-14)


def test_rk4_substeps_follow_the_exact_flow():
    """The continuous plant's discrete map is close to a tight-tolerance ODE solution."""
    dyn = NonlinearDynamics(VAN_DER_POL, VDP_DT)
    theta = jnp.asarray(VAN_DER_POL.theta())
    (mu,) = VAN_DER_POL.theta()
    step = jax.jit(dyn.step_fn)
    f_fine = vdp_numpy(VAN_DER_POL.theta(), substeps=200)[0]
    rng = np.random.default_rng(3)
    u = np.array([0.3])
    for x in rng.uniform(-2.5, 2.5, size=(5, 2)):
        exact = scipy.integrate.solve_ivp(
            lambda t, z: [z[1], mu * (1 - z[0] ** 2) * z[1] - z[0] + u[0]],
            (0.0, VDP_DT),
            x,
            method="DOP853",
            rtol=1e-13,
            atol=1e-13,
        ).y[:, -1]
        engine = np.asarray(step(jnp.asarray(x), jnp.asarray(u), theta))
        # RK4 local error with h = 0.01 on an O(10) field: ~1e-8; generous bound.
        np.testing.assert_allclose(engine, exact, rtol=0, atol=1e-6)
        np.testing.assert_allclose(f_fine(x, u), exact, rtol=0, atol=1e-11)


# ---------------------------------------------------------------------------
# the actuator scenario shared by the tests below


def short_sim1(*, duration=SHORT_DURATION, event_times=SHORT_EVENT_TIMES, **decision):
    data = scenario_to_dict(uimm_jax.load_scenario(SIM1_TUNED))
    data["filter"]["method"] = "uimm"  # these tests are of the fixed-size UIMM's hand-over
    data["filter"].pop("est", None)  # the tuned file's uimm-est settings
    data["name"] += "-short"
    data["duration"] = duration
    for event, time in zip(data["events"], event_times, strict=True):
        event["time"] = time
    data["filter"]["decision"].update(decision)
    return parse_scenario(data)


@pytest.fixture(scope="module")
def sim1_setup():
    return run.setup_scenario(short_sim1())


@pytest.fixture(scope="module")
def sim1(sim1_setup):
    truth = run.simulate_scenario(sim1_setup, chunk=CHUNK)
    final, out = run.filter_measurements(
        sim1_setup, truth["y"], truth["u"], chunk=CHUNK, with_cov=True
    )
    return SimpleNamespace(setup=sim1_setup, truth=truth, final=final, out=out)


# ---------------------------------------------------------------------------
# exact zero-order hold of the hydraulic actuator


def actuator_zoh(theta, dt):
    """``expm([[A, B], [0, 0]] dt)`` from design.md section 1, with scipy."""
    p = dict(zip(HYDRAULIC_ACTUATOR.param_names, theta, strict=True))
    A = np.array(
        [
            [0.0, 1.0, 0.0],
            [-p["Kh"] / p["mh"], -p["Bh"] / p["mh"], p["Ah"] / p["mh"]],
            [0.0, -4 * p["Eh"] * p["Ah"] / p["Vh"], -4 * p["Eh"] * (p["Kc"] + p["Cl"]) / p["Vh"]],
        ]
    )
    B = np.array([[0.0], [0.0], [4 * p["Eh"] * p["Kv"] * p["Kq"] / p["Vh"]]])
    aug = np.zeros((4, 4))
    aug[:3, :3] = A
    aug[:3, 3:] = B
    E = scipy.linalg.expm(aug * dt)
    return E[:3, :3], E[:3, 3:]


def theta_with_faults(scenario, faults):
    """Parameter vector with the named faults' values of the scenario's library."""
    theta = HYDRAULIC_ACTUATOR.theta(scenario.plant_params)
    names = HYDRAULIC_ACTUATOR.param_names
    for fault in faults:
        for name, value in scenario.faults[fault].items():
            theta[names.index(name)] = value
    return theta


@pytest.mark.parametrize("library", ["scenario", "full"])
def test_zoh_equals_expm_for_every_fault_parameter_set(library, sim1_setup):
    dt = float(sim1_setup.scenario.dt)
    if library == "scenario":
        # the dynamics the runs use, on every subset of the paper's faults
        dyn = sim1_setup.diagnoser.dyn
        names = list(sim1_setup.scenario.faults)
        thetas = [
            theta_with_faults(
                sim1_setup.scenario, [f for f, on in zip(names, s, strict=True) if on]
            )
            for s in itertools.product([False, True], repeat=len(names))
        ]
    else:
        # nominal and each fault of the plant's full library (paper + extra)
        faults = PAPER_FAULTS + EXTRA_FAULTS
        nominal = HYDRAULIC_ACTUATOR.theta()
        thetas = [nominal] + [HYDRAULIC_ACTUATOR.theta(dict(f.values)) for f in faults]
        dyn = make_dynamics(HYDRAULIC_ACTUATOR, dt, np.array(thetas))
    thetas = np.array(thetas)
    cache = jax.jit(dyn.prepare)(jnp.asarray(thetas.T))
    for i, theta in enumerate(thetas):
        Ad, Bd = actuator_zoh(theta, dt)
        np.testing.assert_allclose(np.asarray(cache.A)[..., i], Ad, rtol=1e-12, err_msg=str(i))
        np.testing.assert_allclose(np.asarray(cache.B)[..., i], Bd, rtol=1e-12, err_msg=str(i))


# ---------------------------------------------------------------------------
# the actuator UIMM on a short variant of paper_sim1_tuned


def test_uimm_with_nothing_declared_equals_imm_on_the_same_bank(sim1):
    setup = run.setup_scenario(short_sim1(threshold=1.0, hold=NEVER))
    assert setup.diagnoser is sim1.setup.diagnoser  # same compiled chunk
    y, u = sim1.truth["y"], sim1.truth["u"]
    _, out = run.filter_measurements(setup, y, u, chunk=CHUNK, with_cov=True)
    assert np.all(out["declared"] == 0)
    cache = setup.diagnoser.prepare(jnp.zeros(3, bool), jnp.float64)
    M = setup.diagnoser.num_models
    sc = setup.scenario
    fb = uimm_jax.LinearGaussianBank(
        np.moveaxis(np.asarray(cache.A), -1, 0),
        np.moveaxis(np.asarray(cache.B), -1, 0),
        np.broadcast_to(np.eye(3), (M, 3, 3)),
        np.broadcast_to(sc.process_noise, (M, 3, 3)),
        np.broadcast_to(sc.measurement_noise, (M, 3, 3)),
    )
    ref = uimm_jax.imm_filter(
        fb,
        setup.transition,
        setup.initial_mode_probs,
        sc.filter.initial_mean,
        sc.filter.initial_cov,
        u,
        y,
        gate=setup.diagnoser.gate,  # the scenario's innovation gate, if any
    )
    mode_probs = np.asarray(ref.mode_probs)
    # the comparison is informative: each fault model dominates at some point
    assert np.all(mode_probs.max(axis=0) > 0.9)
    np.testing.assert_allclose(out["mode_probs"], mode_probs, rtol=0, atol=1e-10)
    # states span ~9 decades (m, m/s, Pa): compare each on its own scale
    scale = np.abs(np.asarray(ref.mean)).max(axis=0)
    np.testing.assert_allclose(
        out["mean"] / scale, np.asarray(ref.mean) / scale, rtol=0, atol=1e-10
    )
    std = np.sqrt(np.einsum("kii->ki", np.asarray(ref.cov)).max(axis=0))
    outer = np.outer(std, std)
    np.testing.assert_allclose(out["cov"] / outer, np.asarray(ref.cov) / outer, rtol=0, atol=1e-10)


def test_declared_faults_never_retract_and_are_the_true_ones(sim1):
    declared = sim1.out["declared"].astype(np.int64)
    previous = np.concatenate([[0], declared[:-1]])
    assert np.all(previous & ~declared == 0), "a declared fault was retracted"
    names = list(sim1.setup.table.names)
    truth = sim1.truth["truth"].astype(np.int64)
    assert declared[-1] == truth[-1]  # every true fault declared, nothing else
    for event, k_event in zip(sim1.setup.scenario.events, sim1.setup.event_steps, strict=True):
        bit = 1 << names.index(event.fault)
        k_declared = int(np.argmax(declared & bit > 0))
        assert k_declared >= k_event, f"{event.fault} declared before it happened"
        # wide bound: the tuned filter declares within tens of milliseconds
        assert (k_declared - k_event) * sim1.setup.scenario.dt < 1.0, event.fault
    final = np.asarray(sim1.final.declared)
    np.testing.assert_array_equal(final, [(declared[-1] >> j) & 1 for j in range(len(names))])


def test_long_run_probabilities_sum_to_one_and_covariances_stay_psd(sim1):
    out = sim1.out
    assert out["mode_probs"].shape[0] == round(SHORT_DURATION / sim1.setup.scenario.dt)
    for key in ("mode_probs", "mean", "cov"):
        assert np.all(np.isfinite(out[key])), key
    assert np.all(out["mode_probs"] >= 0.0)
    np.testing.assert_allclose(out["mode_probs"].sum(axis=1), 1.0, rtol=0, atol=1e-12)
    assert_symmetric_psd(out["cov"], "combined covariance")
    model_cov = np.moveaxis(np.asarray(sim1.final.imm.cov), -1, 0)
    assert_symmetric_psd(model_cov, "final per-model covariances")
    assert np.all(out["health"] & imm.HEALTH_NONFINITE == 0)


def test_missing_measurements_follow_the_markov_prediction(sim1):
    y = sim1.truth["y"].copy()
    stretches = [(5_000, 7_000), (100_000, 102_000)]  # before any event; after both
    for a, b in stretches:
        y[a:b] = np.nan
    _, out = run.filter_measurements(sim1.setup, y, sim1.truth["u"], chunk=CHUNK, with_cov=True)
    for key in ("mode_probs", "mean", "cov"):
        assert not np.any(np.isnan(out[key])), key
    missing = np.zeros(y.shape[0], bool)
    for a, b in stretches:
        missing[a:b] = True
    np.testing.assert_array_equal(out["health"] & imm.HEALTH_MISSING > 0, missing)
    transition = sim1.setup.transition
    F = sim1.setup.diagnoser.num_faults
    for a, b in stretches:
        code = out["declared"][a - 2]
        assert np.all(out["declared"][a - 2 : b] == code)  # no hand-over in or just before
        active = np.array([True] + [not (code >> j) & 1 for j in range(F)])
        c = out["mode_probs"][a - 1 : b - 1] @ transition
        expected = np.where(active, c, 0.0)
        expected /= expected.sum(axis=1, keepdims=True)
        np.testing.assert_allclose(out["mode_probs"][a:b], expected, rtol=1e-12, atol=1e-15)
        # the data carried no evidence: the probabilities really drifted
        assert np.abs(out["mode_probs"][b - 1] - out["mode_probs"][a - 1]).max() > 0.05
    np.testing.assert_array_equal(out["mode_probs"][:5_000], sim1.out["mode_probs"][:5_000])
    assert out["declared"][-1] == sim1.out["declared"][-1]  # it still diagnoses afterwards


# ---------------------------------------------------------------------------
# UIMM declaration hand-over (one jitted step)

_diag_step = jax.jit(lambda diag, *a: diag.step(*a), static_argnums=0)


def handover_state(setup, declared, mode_probs, seed=0):
    """A diagnoser state with distinct per-model means and covariances."""
    rng = np.random.default_rng(seed)
    M = setup.diagnoser.num_models
    scale = np.array([1e-3, 1e-2, 1e5])  # m, m/s, Pa
    means = scale[:, None] * rng.standard_normal((3, M))
    covs = []
    for _ in range(M):
        G = rng.standard_normal((3, 3))
        covs.append(np.outer(scale, scale) * 1e-2 * (G @ G.T + np.eye(3)))
    covs = np.array(covs)
    with np.errstate(divide="ignore"):
        log_mu = np.log(mode_probs)
    declared = jnp.asarray(declared)
    state = DiagState(
        imm.IMMState(
            jnp.asarray(means), jnp.asarray(np.moveaxis(covs, 0, -1)), jnp.asarray(log_mu)
        ),
        setup.diagnoser.prepare(declared, jnp.float64),
        declared,
        jnp.asarray(0, jnp.int32),
        jnp.asarray(0, jnp.int32),
    )
    return state, means.T, covs


def bank_thetas(scenario, declared):
    """Expected UIMM bank [D, D+f1, ..., D+fF] as parameter vectors, from the scenario."""
    names = list(scenario.faults)
    D = [f for f, on in zip(names, declared, strict=True) if on]
    return np.array(
        [theta_with_faults(scenario, D)] + [theta_with_faults(scenario, D + [f]) for f in names]
    )


@pytest.mark.parametrize(
    "declared_before, winner",
    [
        ((False, False, False), 1),
        ((True, False, False), 2),
        ((True, False, False), 3),
        ((True, True, False), 3),  # the last fault: the bank collapses to model 0
    ],
    ids=["first", "second", "other-second", "last"],
)
def test_declaration_hands_over_to_model_zero(sim1_setup, declared_before, winner):
    setup = sim1_setup
    diag, sc = setup.diagnoser, setup.scenario
    active = np.array((True,) + tuple(not d for d in declared_before))
    mu = np.where(active, 0.1, 0.0)
    mu[winner] = 0.7
    mu /= mu.sum()
    state, means, covs = handover_state(setup, declared_before, mu)
    params = setup.params._replace(threshold=jnp.asarray(0.5), hold=jnp.asarray(1, jnp.int32))
    u = np.array([0.004])
    new, info = _diag_step(diag, state, params, jnp.asarray(u), jnp.full(3, jnp.nan))

    # reference: Markov prediction (no data), masked to the active models
    T = setup.transition
    c = mu @ T
    post = np.where(active, c, 0.0) / np.where(active, c, 0.0).sum()
    assert post.argmax() == winner and post[winner] >= 0.5  # the premise
    expected_mu = post.copy()
    expected_mu[0] = post[winner]
    expected_mu[winner] = 0.0
    expected_mu /= expected_mu.sum()
    np.testing.assert_allclose(np.exp(new.imm.log_mode_probs), expected_mu, rtol=1e-12, atol=0)
    assert np.exp(new.imm.log_mode_probs)[winner] == 0.0

    # every model restarts from the winner's posterior (= its prediction: y is missing)
    w = T[:, winner] * mu / c[winner]
    x0 = w @ means
    d = means - x0
    P0 = np.einsum("i,iab->ab", w, covs + d[:, :, None] * d[:, None, :])
    Ad, Bd = actuator_zoh(bank_thetas(sc, declared_before)[winner], float(sc.dt))
    x_pred = Ad @ x0 + Bd @ u
    P_pred = Ad @ P0 @ Ad.T + sc.process_noise
    for j in range(diag.num_models):
        np.testing.assert_allclose(np.asarray(new.imm.mean)[:, j], x_pred, rtol=1e-10)
        np.testing.assert_allclose(np.asarray(new.imm.cov)[..., j], P_pred, rtol=1e-10)

    # the declared set, the decision outputs and the rebuilt bank
    declared_after = np.array(declared_before)
    declared_after[winner - 1] = True
    np.testing.assert_array_equal(np.asarray(new.declared), declared_after)
    assert bool(info.declared_now)
    assert int(info.declared) == int(np.sum(declared_after * (1 << np.arange(3))))
    assert int(new.run_len) == 0
    thetas = bank_thetas(sc, declared_after)
    built = np.asarray(
        bank.thetas_for_sets(setup.table, diag.model_sets(jnp.asarray(declared_after)))
    )
    np.testing.assert_array_equal(built.T, thetas)  # the fault values are in every model
    for j, theta in enumerate(thetas):
        Ad, Bd = actuator_zoh(theta, float(sc.dt))
        np.testing.assert_allclose(np.asarray(new.cache.A)[..., j], Ad, rtol=1e-12)
        np.testing.assert_allclose(np.asarray(new.cache.B)[..., j], Bd, rtol=1e-12)


def test_no_declaration_before_hold_leaves_the_bank_unchanged(sim1_setup):
    setup = sim1_setup
    diag = setup.diagnoser
    mu = np.array([0.1, 0.7, 0.1, 0.1])
    state, _, _ = handover_state(setup, (False, False, False), mu)
    params = setup.params._replace(threshold=jnp.asarray(0.5), hold=jnp.asarray(2, jnp.int32))
    new, info = _diag_step(diag, state, params, jnp.asarray([0.004]), jnp.full(3, jnp.nan))
    assert not bool(info.declared_now)
    assert not np.any(np.asarray(new.declared))
    assert int(new.run_model) == 1 and int(new.run_len) == 1
    for old, fresh in zip(jax.tree.leaves(state.cache), jax.tree.leaves(new.cache), strict=True):
        np.testing.assert_array_equal(np.asarray(fresh), np.asarray(old))
    expected = mu @ setup.transition
    np.testing.assert_allclose(np.exp(new.imm.log_mode_probs), expected, rtol=1e-12)


# ---------------------------------------------------------------------------
# bank sizes


def library_table(F):
    """Fault table of the actuator's first ``F`` library faults (paper, then extra)."""
    faults = (PAPER_FAULTS + EXTRA_FAULTS)[:F]
    table = uimm_jax.fault_table(
        HYDRAULIC_ACTUATOR.param_names,
        HYDRAULIC_ACTUATOR.theta(),
        {f.name: dict(f.values) for f in faults},
    )
    return table, faults


@pytest.mark.parametrize("F", [1, 2, 3, 4, 5])
def test_combinatorial_bank_has_two_to_the_f_models(F):
    table, _ = library_table(F)
    combinatorial = build_diagnoser("imm", None, table)
    updated = build_diagnoser("uimm", None, table)
    assert combinatorial.num_models == 2**F == len(combinatorial.model_labels())
    assert updated.num_models == F + 1 == len(updated.model_labels())
    sets = bank.combinatorial_sets(F)  # (F, 2^F): fault axis first, like every set
    assert sets.shape == (F, 2**F)
    assert len({tuple(s) for s in sets.T.tolist()}) == 2**F  # every subset exactly once
    codes = np.asarray(bank.set_codes(jnp.asarray(sets)))
    assert len(set(codes.tolist())) == 2**F
    np.testing.assert_array_equal(codes, (1 << np.arange(F)) @ sets)  # bit j = fault j


def test_bank_parameters_are_the_masked_updates_of_each_fault_set():
    F = 5
    table, faults = library_table(F)
    sets = bank.combinatorial_sets(F)
    thetas = np.asarray(bank.thetas_for_sets(table, jnp.asarray(sets)))
    for s, fault_set in enumerate(sets.T):
        changed = {
            k: v for f, on in zip(faults, fault_set, strict=True) if on for k, v in f.values.items()
        }
        np.testing.assert_array_equal(thetas[:, s], HYDRAULIC_ACTUATOR.theta(changed))
    updated = build_diagnoser("uimm", None, table)
    D = np.arange(F) % 2 == 0  # faults 0, 2, 4 declared
    expected = D[None, :] | np.vstack([np.zeros(F, bool), np.eye(F, dtype=bool)])  # (M, F)
    np.testing.assert_array_equal(np.asarray(updated.model_sets(jnp.asarray(D))), expected.T)


# ---------------------------------------------------------------------------
# compilation


def test_no_recompilation_on_a_second_run_with_new_data():
    # a length used by no other test, so the first call must compile
    scenario = short_sim1(duration=0.5, event_times=(0.1, 0.2))
    with count_backend_compiles() as compiles:
        first = uimm_jax.run_scenario(scenario, seed=1)
    assert compiles, "the first call compiled nothing: this check cannot detect recompilation"
    with count_backend_compiles() as compiles:
        second = uimm_jax.run_scenario(scenario, seed=2)
        setup = run.setup_scenario(scenario)
        other = run.simulate_scenario(setup, seed=3)
        _, out = run.filter_measurements(setup, other["y"], other["u"])
    assert compiles == [], f"a second call with same shapes recompiled: {compiles}"
    assert not np.array_equal(first.truth["y"], second.truth["y"])  # new data
    assert not np.array_equal(out["mode_probs"], second.outputs["mode_probs"])
