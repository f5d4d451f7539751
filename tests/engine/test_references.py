"""Validate the test references themselves: naive loop vs filterpy vs vectorised NumPy vs KF."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from _baselines import filterpy_imm, vectorised_numpy_imm  # noqa: E402
from _reference import kalman_filter, make_linear_problem, naive_imm  # noqa: E402

SEEDS = [0, 42, 99]
LOG_FLOAT_MIN = np.log(sys.float_info.min)


@pytest.fixture(scope="module", params=SEEDS)
def problem_and_naive(request):
    problem = make_linear_problem(request.param)
    return problem, naive_imm(**problem)


def test_problem_is_well_formed():
    problem = make_linear_problem(0, M=4, n=3, m=2, p=2, N=50)
    M, n, m, p, N = 4, 3, 2, 2, 50
    assert problem["A"].shape == (M, n, n)
    assert problem["B"].shape == (M, n, p)
    assert problem["C"].shape == (M, m, n)
    assert problem["Q"].shape == (M, n, n)
    assert problem["R"].shape == (M, m, m)
    assert problem["x0"].shape == (M, n)
    assert problem["P0"].shape == (M, n, n)
    assert problem["inputs"].shape == (N, p)
    assert problem["measurements"].shape == (N, m)
    np.testing.assert_allclose(problem["transition"].sum(axis=1), 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(problem["mu0"].sum(), 1.0, rtol=0, atol=1e-14)
    assert np.all(np.linalg.norm(problem["A"], ord=2, axis=(1, 2)) < 1.0)
    for key in ("Q", "R", "P0"):
        assert np.all(np.linalg.eigvalsh(problem[key]) > 0.0)
    # deterministic in the seed
    again = make_linear_problem(0, M=4, n=3, m=2, p=2, N=50)
    for key, value in problem.items():
        np.testing.assert_array_equal(value, again[key])


def test_mode_probabilities_move(problem_and_naive):
    """The problem is informative: some model becomes clearly dominant, and not always the same."""
    _, ref = problem_and_naive
    assert ref["mode_probs"].max() > 0.7
    assert len(np.unique(ref["mode_probs"].argmax(axis=1))) > 1


def test_filterpy_clamp_does_not_fire(problem_and_naive):
    problem, ref = problem_and_naive
    assert np.all(ref["model_loglik"] > LOG_FLOAT_MIN + 100.0)
    fp = filterpy_imm(**problem)
    assert np.all(fp["model_loglik"] > LOG_FLOAT_MIN + 100.0)
    np.testing.assert_allclose(fp["model_loglik"], ref["model_loglik"], rtol=1e-9, atol=1e-9)


def test_naive_matches_filterpy(problem_and_naive):
    problem, ref = problem_and_naive
    fp = filterpy_imm(**problem)
    np.testing.assert_allclose(fp["mode_probs"], ref["mode_probs"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(fp["mean"], ref["mean"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(fp["cov"], ref["cov"], rtol=1e-9, atol=1e-9)


def test_naive_matches_vectorised(problem_and_naive):
    problem, ref = problem_and_naive
    vec = vectorised_numpy_imm(**problem)
    for key in ("mode_probs", "mean", "cov", "model_mean", "model_cov", "model_loglik"):
        np.testing.assert_allclose(vec[key], ref[key], rtol=1e-10, atol=1e-10, err_msg=key)
    np.testing.assert_allclose(vec["marginal_loglik"], ref["marginal_loglik"], rtol=1e-10)


@pytest.mark.parametrize("dims", [dict(M=5, n=3, m=2, p=2), dict(M=2, n=1, m=1, p=1)])
def test_naive_matches_vectorised_and_filterpy_other_shapes(dims):
    problem = make_linear_problem(7, N=100, **dims)
    ref = naive_imm(**problem)
    vec = vectorised_numpy_imm(**problem)
    fp = filterpy_imm(**problem)
    assert np.all(ref["model_loglik"] > LOG_FLOAT_MIN + 100.0)
    for key in ("mode_probs", "mean", "cov"):
        np.testing.assert_allclose(vec[key], ref[key], rtol=1e-10, atol=1e-10, err_msg=key)
        np.testing.assert_allclose(fp[key], ref[key], rtol=1e-9, atol=1e-9, err_msg=key)


def test_mode_probabilities_sum_to_one(problem_and_naive):
    _, ref = problem_and_naive
    np.testing.assert_allclose(ref["mode_probs"].sum(axis=1), 1.0, rtol=0, atol=1e-13)
    assert np.all(ref["mode_probs"] >= 0.0)
    np.testing.assert_allclose(np.exp(ref["log_mode_probs"]), ref["mode_probs"], rtol=1e-13)


def test_marginal_loglik_is_sum_of_mixture_terms(problem_and_naive):
    """Recompute sum_k log sum_j exp(ll_kj) c_kj from the outputs (c_k = mu_{k-1} @ P)."""
    problem, ref = problem_and_naive
    prev = np.vstack([problem["mu0"], ref["mode_probs"][:-1]])
    c = prev @ problem["transition"]
    total = np.log((np.exp(ref["model_loglik"]) * c).sum(axis=1)).sum()
    np.testing.assert_allclose(ref["marginal_loglik"], total, rtol=1e-10)


@pytest.mark.parametrize("seed", SEEDS)
def test_one_model_naive_imm_is_a_kalman_filter(seed):
    problem = make_linear_problem(seed, M=1, n=3, m=2, p=1, N=150)
    ref = naive_imm(**problem)
    kf = kalman_filter(
        problem["A"][0],
        problem["B"][0],
        problem["C"][0],
        problem["Q"][0],
        problem["R"][0],
        problem["x0"][0],
        problem["P0"][0],
        problem["inputs"],
        problem["measurements"],
    )
    np.testing.assert_array_equal(ref["mode_probs"], 1.0)
    np.testing.assert_allclose(ref["mean"], kf["mean"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(ref["cov"], kf["cov"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(ref["model_loglik"][:, 0], kf["loglik"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(ref["marginal_loglik"], kf["marginal_loglik"], rtol=1e-10)
    vec = vectorised_numpy_imm(**problem)
    np.testing.assert_allclose(vec["mean"], kf["mean"], rtol=1e-10, atol=1e-12)


def _with_nans(problem, rows, channel=None):
    out = dict(problem)
    y = problem["measurements"].copy()
    if channel is None:
        y[rows] = np.nan
    else:
        y[rows, channel] = np.nan
    out["measurements"] = y
    return out


def test_missing_rows_are_predict_only():
    problem = make_linear_problem(3, M=3, n=2, m=2, p=1, N=60)
    rows = [0, 10, 11, 12, 40]
    missing = _with_nans(problem, rows)
    ref = naive_imm(**missing)
    vec = vectorised_numpy_imm(**missing)
    for key in ("mode_probs", "mean", "cov", "model_loglik"):
        np.testing.assert_allclose(vec[key], ref[key], rtol=1e-10, atol=1e-10, err_msg=key)
    np.testing.assert_array_equal(ref["model_loglik"][rows], 0.0)
    prev = np.vstack([problem["mu0"], ref["mode_probs"][:-1]])
    markov = prev @ problem["transition"]
    np.testing.assert_allclose(ref["mode_probs"][rows], markov[rows], rtol=1e-12, atol=1e-15)


def test_missing_channel_equals_dropped_channel():
    problem = make_linear_problem(5, M=3, n=2, m=2, p=1, N=60)
    all_rows = np.arange(60)
    missing = _with_nans(problem, all_rows, channel=1)
    dropped = dict(problem)
    dropped["C"] = problem["C"][:, :1, :]
    dropped["R"] = problem["R"][:, :1, :1]
    dropped["measurements"] = problem["measurements"][:, :1]
    ref_missing = naive_imm(**missing)
    ref_dropped = naive_imm(**dropped)
    vec_missing = vectorised_numpy_imm(**missing)
    fp_dropped = filterpy_imm(**dropped)
    for key in ("mode_probs", "mean", "cov"):
        np.testing.assert_allclose(ref_missing[key], ref_dropped[key], rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(vec_missing[key], ref_dropped[key], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(fp_dropped[key], ref_dropped[key], rtol=1e-9, atol=1e-9)


def test_zero_column_transition_is_finite():
    problem = make_linear_problem(11, M=3, N=80)
    problem["transition"] = np.array([[1.0, 0.0, 0.0], [0.1, 0.9, 0.0], [0.5, 0.5, 0.0]])
    ref = naive_imm(**problem)
    vec = vectorised_numpy_imm(**problem)
    for key in ("mode_probs", "mean", "cov"):
        assert np.all(np.isfinite(ref[key])), key
        np.testing.assert_allclose(vec[key], ref[key], rtol=1e-10, atol=1e-10, err_msg=key)
    np.testing.assert_array_equal(ref["mode_probs"][:, 2], 0.0)
    assert np.isfinite(ref["marginal_loglik"])
