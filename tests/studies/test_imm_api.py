"""Public API of the linear-Gaussian IMM engine against independent references.

Contract: ``uimm_jax.LinearGaussianBank(A, B, C, Q, R)`` (discrete time, leading model
axis) and ``uimm_jax.imm_filter(bank, transition, initial_mode_probs, initial_mean,
initial_cov, inputs, measurements)`` returning an object with ``mode_probs (N,M)``,
``log_mode_probs (N,M)``, ``mean (N,n)``, ``cov (N,n,n)``, ``model_loglik (N,M)`` and
``marginal_loglik`` (scalar).  References: ``tests/_reference.py`` (naive loop, KF) and
``benchmarks/_baselines.py`` (vectorised NumPy, filterpy), validated in
``tests/test_references.py``.
"""

import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import uimm_jax

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from _baselines import filterpy_imm, vectorised_numpy_imm  # noqa: E402
from _engine_helpers import count_backend_compiles  # noqa: E402
from _reference import kalman_filter, make_linear_problem, naive_imm  # noqa: E402

SEEDS = [0, 42, 99]
LOG_FLOAT_MIN = np.log(sys.float_info.min)


def run_engine(problem, *, initial_mean=None, initial_cov=None):
    """Call the engine on a ``make_linear_problem``-style dict; outputs as NumPy."""
    bank = uimm_jax.LinearGaussianBank(
        problem["A"], problem["B"], problem["C"], problem["Q"], problem["R"]
    )
    result = uimm_jax.imm_filter(
        bank,
        problem["transition"],
        problem["mu0"],
        problem["x0"] if initial_mean is None else initial_mean,
        problem["P0"] if initial_cov is None else initial_cov,
        problem["inputs"],
        problem["measurements"],
    )
    keys = ("mode_probs", "log_mode_probs", "mean", "cov", "model_loglik", "marginal_loglik")
    return {key: np.asarray(getattr(result, key)) for key in keys}


def assert_matches_naive(out, ref, *, rtol=1e-10, atol=1e-10, keys=None):
    keys = keys or ("mode_probs", "mean", "cov", "model_loglik")
    for key in keys:
        np.testing.assert_allclose(out[key], ref[key], rtol=rtol, atol=atol, err_msg=key)


def markov_prediction(mu0, mode_probs, transition):
    """c_k = mu_{k-1} @ P for every k, from the filter's own previous probabilities."""
    previous = np.vstack([np.asarray(mu0)[None, :], mode_probs[:-1]])
    return previous @ transition


def with_missing(problem, rows, channel=None):
    out = dict(problem)
    y = np.array(problem["measurements"], dtype=np.float64)
    if channel is None:
        y[rows] = np.nan
    else:
        y[rows, channel] = np.nan
    out["measurements"] = y
    return out


def shared_dynamics(problem):
    """Same A and B in every model (Q, C, R, x0, P0 still differ)."""
    out = dict(problem)
    M = problem["A"].shape[0]
    out["A"] = np.repeat(problem["A"][:1], M, axis=0)
    out["B"] = np.repeat(problem["B"][:1], M, axis=0)
    return out


# ---------------------------------------------------------------------------
# agreement with the references


@pytest.mark.parametrize("seed", SEEDS)
def test_matches_filterpy(seed):
    problem = make_linear_problem(seed)
    fp = filterpy_imm(**problem)
    # filterpy's linear-space clamp must not fire, or it is not a valid reference
    assert np.all(fp["model_loglik"] > LOG_FLOAT_MIN + 100.0)
    out = run_engine(problem)
    np.testing.assert_allclose(out["mode_probs"], fp["mode_probs"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out["mean"], fp["mean"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(out["cov"], fp["cov"], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
def test_matches_naive(seed):
    problem = make_linear_problem(seed)
    ref = naive_imm(**problem)
    out = run_engine(problem)
    assert_matches_naive(out, ref)
    np.testing.assert_allclose(out["marginal_loglik"], ref["marginal_loglik"], rtol=1e-10)
    # log_mode_probs where the probability is representable (else both may be -inf-ish)
    keep = ref["mode_probs"] > 1e-100
    np.testing.assert_allclose(
        out["log_mode_probs"][keep], ref["log_mode_probs"][keep], rtol=1e-9, atol=1e-9
    )
    np.testing.assert_allclose(np.exp(out["log_mode_probs"]), out["mode_probs"], rtol=1e-12)


@pytest.mark.parametrize("dims", [dict(M=5, n=3, m=2, p=2), dict(M=2, n=1, m=1, p=1)])
def test_matches_naive_other_shapes(dims):
    problem = make_linear_problem(7, N=100, **dims)
    ref = naive_imm(**problem)
    out = run_engine(problem)
    assert_matches_naive(out, ref)
    np.testing.assert_allclose(out["marginal_loglik"], ref["marginal_loglik"], rtol=1e-10)


def test_output_shapes():
    M, n, m, p, N = 5, 3, 2, 2, 100
    problem = make_linear_problem(1, M=M, n=n, m=m, p=p, N=N)
    out = run_engine(problem)
    assert out["mode_probs"].shape == (N, M)
    assert out["log_mode_probs"].shape == (N, M)
    assert out["mean"].shape == (N, n)
    assert out["cov"].shape == (N, n, n)
    assert out["model_loglik"].shape == (N, M)
    assert out["marginal_loglik"].shape == ()
    for key, value in out.items():
        assert value.dtype == np.float64, key


@pytest.mark.parametrize("gate", [None, 9.0])
def test_without_cov_the_other_outputs_are_unchanged(gate):
    """``return_cov=False`` drops the combined covariance and nothing else, bit for bit."""
    problem = with_missing(make_linear_problem(4, M=3, n=3, m=2, p=1, N=200), [5, 6], channel=1)
    bank = uimm_jax.LinearGaussianBank(
        problem["A"], problem["B"], problem["C"], problem["Q"], problem["R"]
    )
    args = (bank, problem["transition"], problem["mu0"], problem["x0"], problem["P0"])
    data = (problem["inputs"], problem["measurements"])
    full = uimm_jax.imm_filter(*args, *data, gate=gate, return_model_means=True)
    lean = uimm_jax.imm_filter(*args, *data, gate=gate, return_model_means=True, return_cov=False)
    assert lean.cov is None and full.cov.shape == (200, 3, 3)
    for key in full._fields:
        if key != "cov":
            np.testing.assert_array_equal(getattr(lean, key), getattr(full, key), err_msg=key)


def test_selected_outputs_are_the_default_ones_bit_for_bit():
    """``outputs=`` computes the named fields, bit for bit the default call's, and no other.

    ``mode_probs`` without ``log_mode_probs``, ``marginal_loglik`` without the increments:
    the fields the scan keeps only for them.  The problem and the default call are
    ``test_without_cov_the_other_outputs_are_unchanged``'s (compiled there).
    """
    outputs = ("model_mean", "mode_probs", "cov", "marginal_loglik")
    problem = with_missing(make_linear_problem(4, M=3, n=3, m=2, p=1, N=200), [5, 6], channel=1)
    bank = uimm_jax.LinearGaussianBank(
        problem["A"], problem["B"], problem["C"], problem["Q"], problem["R"]
    )
    args = (bank, problem["transition"], problem["mu0"], problem["x0"], problem["P0"])
    data = (problem["inputs"], problem["measurements"])
    full = uimm_jax.imm_filter(*args, *data, gate=9.0, return_model_means=True)
    some = uimm_jax.imm_filter(*args, *data, gate=9.0, outputs=outputs)
    assert isinstance(some, uimm_jax.IMMResult)
    for key in full._fields:
        if key in outputs:
            np.testing.assert_array_equal(getattr(some, key), getattr(full, key), err_msg=key)
        else:
            assert getattr(some, key) is None, key


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(outputs=("mean", "covariance")), "unknown names \\['covariance'\\]"),
        (dict(outputs="mean"), "tuple of field names"),
        (dict(outputs=()), "no name given"),
        (dict(outputs=("mean",), return_cov=False), "either outputs or return_cov"),
        (dict(outputs=("mean",), return_model_means=True), "either outputs or return_cov"),
    ],
)
def test_bad_outputs_are_refused_by_name(kwargs, match):
    problem = make_linear_problem(0, N=5)
    bank = uimm_jax.LinearGaussianBank(
        problem["A"], problem["B"], problem["C"], problem["Q"], problem["R"]
    )
    args = (bank, problem["transition"], problem["mu0"], problem["x0"], problem["P0"])
    with pytest.raises(ValueError, match=match):
        uimm_jax.imm_filter(*args, problem["inputs"], problem["measurements"], **kwargs)


def test_shared_initial_mean_and_cov_broadcast():
    problem = make_linear_problem(8)
    M = problem["A"].shape[0]
    x0, P0 = problem["x0"][1], problem["P0"][1]
    tiled = dict(problem, x0=np.tile(x0, (M, 1)), P0=np.tile(P0, (M, 1, 1)))
    ref = naive_imm(**tiled)
    out = run_engine(problem, initial_mean=x0, initial_cov=P0)
    assert_matches_naive(out, ref)
    mixed = run_engine(problem, initial_mean=x0)  # (n,) mean with (M,n,n) covs
    assert_matches_naive(mixed, naive_imm(**dict(problem, x0=np.tile(x0, (M, 1)))))


# ---------------------------------------------------------------------------
# exact reductions


@pytest.mark.parametrize("seed", SEEDS)
def test_one_model_is_a_kalman_filter(seed):
    problem = make_linear_problem(seed, M=1, n=3, m=2, p=1, N=150)
    kf = kalman_filter(
        *(problem[key][0] for key in ("A", "B", "C", "Q", "R", "x0", "P0")),
        problem["inputs"],
        problem["measurements"],
    )
    out = run_engine(problem)
    np.testing.assert_allclose(out["mode_probs"], 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(out["log_mode_probs"], 0.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(out["mean"], kf["mean"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out["cov"], kf["cov"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out["model_loglik"][:, 0], kf["loglik"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out["marginal_loglik"], kf["marginal_loglik"], rtol=1e-10)


@pytest.mark.parametrize("seed", SEEDS)
def test_identical_models_keep_markov_predicted_probabilities(seed):
    N, M = 200, 3
    base = make_linear_problem(seed, M=1, N=N)
    problem = make_linear_problem(seed, M=M, N=N)  # for transition and mu0
    for key in ("A", "B", "C", "Q", "R", "x0", "P0"):
        problem[key] = np.repeat(base[key], M, axis=0)
    problem["inputs"], problem["measurements"] = base["inputs"], base["measurements"]
    kf = kalman_filter(
        *(base[key][0] for key in ("A", "B", "C", "Q", "R", "x0", "P0")),
        base["inputs"],
        base["measurements"],
    )
    out = run_engine(problem)
    c = markov_prediction(problem["mu0"], out["mode_probs"], problem["transition"])
    np.testing.assert_allclose(out["mode_probs"], c, rtol=1e-12, atol=1e-15)
    # and therefore mu_k = mu0 P^(k+1), independent of the data
    np.testing.assert_allclose(
        out["mode_probs"][-1],
        problem["mu0"] @ np.linalg.matrix_power(problem["transition"], N),
        rtol=1e-10,
    )
    np.testing.assert_allclose(out["mean"], kf["mean"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out["cov"], kf["cov"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out["marginal_loglik"], kf["marginal_loglik"], rtol=1e-10)


# ---------------------------------------------------------------------------
# missing data


def test_missing_rows_follow_the_markov_prediction():
    problem = make_linear_problem(3, m=2)
    rows = [0, 1, 20, 21, 22, 50, 199]
    missing = with_missing(problem, rows)
    out = run_engine(missing)
    assert_matches_naive(out, naive_imm(**missing))
    np.testing.assert_allclose(out["model_loglik"][rows], 0.0, rtol=0, atol=1e-12)
    c = markov_prediction(problem["mu0"], out["mode_probs"], problem["transition"])
    np.testing.assert_allclose(out["mode_probs"][rows], c[rows], rtol=1e-12, atol=1e-15)


def test_missing_rows_give_the_pure_prediction_of_the_mean():
    """With A, B shared by the models, a missing row maps mean[k-1] to A mean[k-1] + B u[k]."""
    problem = shared_dynamics(make_linear_problem(4, M=5, n=3, m=2, p=2, N=100))
    rows = [0, 1, 30, 31, 32, 60, 99]
    out = run_engine(with_missing(problem, rows))
    A, B = problem["A"][0], problem["B"][0]
    previous = np.vstack([problem["mu0"] @ problem["x0"], out["mean"][:-1]])
    predicted = previous @ A.T + problem["inputs"] @ B.T
    np.testing.assert_allclose(out["mean"][rows], predicted[rows], rtol=1e-12, atol=1e-12)


def test_all_missing_is_a_markov_chain_and_a_prediction():
    problem = shared_dynamics(make_linear_problem(6))
    problem["x0"] = np.repeat(problem["x0"][:1], 3, axis=0)
    out = run_engine(with_missing(problem, slice(None)))
    T, mu = problem["transition"], problem["mu0"]
    expected_mu, expected_mean = [], []
    x = problem["x0"][0]
    for u in problem["inputs"]:
        mu = mu @ T
        x = problem["A"][0] @ x + problem["B"][0] @ u
        expected_mu.append(mu)
        expected_mean.append(x)
    np.testing.assert_allclose(out["mode_probs"], expected_mu, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out["mean"], expected_mean, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out["marginal_loglik"], 0.0, rtol=0, atol=1e-12)


def test_partially_missing_measurements_match_naive():
    problem = make_linear_problem(5, m=2)
    missing = with_missing(problem, [2, 3, 40, 120], channel=1)
    missing["measurements"][[10, 40, 41], 0] = np.nan  # row 40: both channels missing
    ref = naive_imm(**missing)
    out = run_engine(missing)
    assert_matches_naive(out, ref)
    np.testing.assert_allclose(out["marginal_loglik"], ref["marginal_loglik"], rtol=1e-10)


def test_always_missing_channel_equals_dropping_it():
    problem = make_linear_problem(5, m=2)
    missing = with_missing(problem, slice(None), channel=1)
    dropped = dict(
        problem,
        C=problem["C"][:, :1, :],
        R=problem["R"][:, :1, :1],
        measurements=problem["measurements"][:, :1],
    )
    out_missing = run_engine(missing)
    out_dropped = run_engine(dropped)
    assert_matches_naive(out_missing, naive_imm(**dropped))
    assert_matches_naive(out_missing, out_dropped, rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------
# properties and robustness


def test_long_run_probabilities_and_covariances_stay_valid():
    problem = make_linear_problem(123, M=4, n=3, m=2, p=1, N=2000)
    out = run_engine(problem)
    for key, value in out.items():
        assert np.all(np.isfinite(value)), key
    np.testing.assert_allclose(out["mode_probs"].sum(axis=1), 1.0, rtol=0, atol=1e-12)
    assert np.all(out["mode_probs"] >= 0.0)
    cov = out["cov"]
    scale = np.abs(cov).max()
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), rtol=0, atol=1e-12 * scale)
    assert np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, 1, 2))).min() > -1e-12 * scale
    # and no drift from the vectorised reference over the long run
    vec = vectorised_numpy_imm(**problem)
    assert_matches_naive(out, vec, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(out["marginal_loglik"], vec["marginal_loglik"], rtol=1e-10)


def test_absorbing_transition_gives_no_nan():
    """An identity row (model 0 absorbing) and a zero column (model 2 unreachable)."""
    problem = make_linear_problem(11)
    problem["transition"] = np.array([[1.0, 0.0, 0.0], [0.1, 0.9, 0.0], [0.5, 0.5, 0.0]])
    problem["mu0"] = np.array([0.2, 0.3, 0.5])
    out = run_engine(problem)
    for key, value in out.items():
        assert not np.any(np.isnan(value)), key
    for key in ("mode_probs", "mean", "cov", "marginal_loglik"):
        assert np.all(np.isfinite(out[key])), key
    np.testing.assert_allclose(out["mode_probs"].sum(axis=1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(out["mode_probs"][:, 2], 0.0)
    ref = naive_imm(**problem)  # combined outputs do not depend on model 2's dead state
    assert_matches_naive(out, ref, keys=("mode_probs", "mean", "cov"))
    np.testing.assert_allclose(out["marginal_loglik"], ref["marginal_loglik"], rtol=1e-10)


@pytest.mark.parametrize("M", [1, 3])
def test_outlier_measurement_stays_finite(M):
    dims = dict(M=1, n=3, m=2, p=1, N=150) if M == 1 else dict(M=M)  # shapes of other tests
    problem = make_linear_problem(21, **dims)
    problem["measurements"][30] = 1e8
    out = run_engine(problem)
    for key in ("mode_probs", "mean", "cov", "marginal_loglik"):
        assert np.all(np.isfinite(out[key])), key
    assert not np.any(np.isnan(out["log_mode_probs"]))
    assert not np.any(np.isnan(out["model_loglik"]))
    np.testing.assert_allclose(out["mode_probs"].sum(axis=1), 1.0, rtol=0, atol=1e-12)
    if M == 1:
        kf = kalman_filter(
            *(problem[key][0] for key in ("A", "B", "C", "Q", "R", "x0", "P0")),
            problem["inputs"],
            problem["measurements"],
        )
        np.testing.assert_allclose(out["mean"], kf["mean"], rtol=1e-9, atol=1e-9)


def test_no_recompilation_for_new_data_of_the_same_shapes():
    # shapes used by no other test, and fresh caches, so the first call must compile
    first = make_linear_problem(31, M=2, n=3, m=2, p=1, N=37)
    second = make_linear_problem(32, M=2, n=3, m=2, p=1, N=37)
    jax.clear_caches()
    with count_backend_compiles() as compiles:
        jax.block_until_ready(run_engine(first)["mean"])
    assert compiles, "the first call compiled nothing: this check cannot detect recompilation"
    with count_backend_compiles() as compiles:
        out = run_engine(second)
    assert compiles == [], f"second call with same shapes recompiled: {compiles}"
    assert_matches_naive(out, naive_imm(**second))


# ---------------------------------------------------------------------------
# the per-step arrays' transfer and the measurements' inf check (fast paths)


def test_transfer_is_a_private_exact_copy():
    from uimm_jax.studies.imm_filter import _to_device

    rng = np.random.default_rng(5)
    for shape in ((1000, 3), (7, 1), (5, 0)):
        # 64-byte aligned, as JAX on a CPU would use it in place (and see later changes)
        raw = np.empty(int(np.prod(shape)) * 8 + 64, np.uint8)
        start = -raw.ctypes.data % 64
        a = raw[start : start + int(np.prod(shape)) * 8].view(np.float64).reshape(shape)
        a[...] = rng.standard_normal(shape)
        keep = a.copy()
        out = _to_device(a, np.float64)
        a[...] = 0.0  # the caller changes its array after the call
        assert out.shape == shape and out.dtype == np.float64
        np.testing.assert_array_equal(np.asarray(out), keep)
    x = np.linspace(0.0, 1.0, 11)[:, None]
    np.testing.assert_array_equal(np.asarray(_to_device(x, np.float32)), x.astype(np.float32))


@pytest.mark.parametrize(
    "values, bad",
    [
        ([1.0, np.nan, np.inf], (2, 0)),  # NaN present: the sum is not finite either way
        ([np.inf, -np.inf, 0.0], (0, 0)),  # inf - inf sums to NaN
        ([1e308, 1e308, -np.inf], (2, 0)),
    ],
)
def test_inf_measurements_refused_with_their_entry(values, bad):
    problem = make_linear_problem(0, M=2, n=1, m=1, p=1, N=3)
    problem["measurements"] = np.asarray(values, dtype=np.float64)[:, None]
    with pytest.raises(ValueError, match=rf"measurements: entry \({bad[0]}, {bad[1]}\) is -?inf"):
        run_engine(problem)


def test_huge_finite_or_missing_measurements_are_accepted():
    problem = make_linear_problem(0, M=2, n=1, m=1, p=1, N=4)
    for values in ([1e308, 1e308, 1.0, 2.0], [np.nan, 1.0, np.nan, 2.0]):  # sum overflows / NaN
        problem["measurements"] = np.asarray(values)[:, None]
        out = run_engine(problem)
        assert np.all(np.isfinite(out["mode_probs"]))


@pytest.mark.parametrize("seed", SEEDS)
def test_nis_is_the_kalman_filters_innovation_quadratic_form_and_off_by_default(seed):
    """``outputs=("nis", ...)``: each model's ``e' S^-1 e`` (eq. 27's quadratic term) is the
    textbook Kalman filter's for one model; the default call leaves it out (``None``), so
    its bytes per step are as measured in benchmarks/README.md."""
    problem = make_linear_problem(seed, M=1, n=3, m=2, p=1, N=150)
    kf = kalman_filter(
        *(problem[key][0] for key in ("A", "B", "C", "Q", "R", "x0", "P0")),
        problem["inputs"],
        problem["measurements"],
    )
    bank = uimm_jax.LinearGaussianBank(
        problem["A"], problem["B"], problem["C"], problem["Q"], problem["R"]
    )
    args = (bank, problem["transition"], problem["mu0"], problem["x0"], problem["P0"])
    data = (problem["inputs"], problem["measurements"])
    out = uimm_jax.imm_filter(*args, *data, outputs=("nis", "model_loglik"))
    assert out.nis.shape == (150, 1)
    np.testing.assert_allclose(out.nis[:, 0], kf["nis"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.model_loglik[:, 0], kf["loglik"], rtol=1e-10, atol=1e-12)
    assert uimm_jax.imm_filter(*args, *data).nis is None


@pytest.mark.parametrize("seed", SEEDS)
def test_nis_channels_are_each_channels_squared_innovation_over_its_variance(seed):
    """``outputs=("nis_channels",)``: each model's ``e_i^2 / S_ii`` per channel equals the
    textbook Kalman filter's; a missing channel gives 0 there while the others keep their
    own terms, and the default call leaves the field out."""
    problem = make_linear_problem(seed, M=1, n=3, m=2, p=1, N=150)
    keys = ("A", "B", "C", "Q", "R", "x0", "P0")
    kf = kalman_filter(
        *(problem[key][0] for key in keys), problem["inputs"], problem["measurements"]
    )
    bank = uimm_jax.LinearGaussianBank(
        problem["A"], problem["B"], problem["C"], problem["Q"], problem["R"]
    )
    args = (bank, problem["transition"], problem["mu0"], problem["x0"], problem["P0"])
    data = (problem["inputs"], problem["measurements"])
    out = uimm_jax.imm_filter(*args, *data, outputs=("nis_channels", "nis"))
    assert out.nis_channels.shape == (150, 1, 2)
    np.testing.assert_allclose(out.nis_channels[:, 0], kf["nis_channels"], rtol=1e-9, atol=1e-12)
    # With uncorrelated channels (S diagonal) the channels' terms add up to e' S^-1 e;
    # in general they do not, which is why both are kept.
    assert not np.allclose(np.sum(out.nis_channels[:, 0], axis=1), out.nis[:, 0])
    y = np.array(problem["measurements"], copy=True)
    y[10:20, 1] = np.nan
    gap = uimm_jax.imm_filter(*args, problem["inputs"], y, outputs=("nis_channels",))
    assert np.all(gap.nis_channels[10:20, 0, 1] == 0.0)
    assert np.all(gap.nis_channels[10:20, 0, 0] > 0.0)
    np.testing.assert_array_equal(gap.nis_channels[:10], out.nis_channels[:10])
    assert uimm_jax.imm_filter(*args, *data).nis_channels is None
