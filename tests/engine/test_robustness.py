"""Robustness (issue 6): validation at every Python entry point and numerical safety.

The long acceptance run (1e6 steps of each shipped scenario with 10 % dropped measurements
and 100 outliers of 1e6 sigma) is ``benchmarks/robustness_long.py``; here the same study
runs on 2e5-step variants of the tuned scenarios.
"""

from __future__ import annotations

import dataclasses
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

from _reference import make_linear_problem, naive_imm
from _robustness_helpers import CHUNK, all_finite, assert_declared_right, short_scenario
from uimm_jax import Fault, fault_table
from uimm_jax.engine.imm import (
    HEALTH_COV_REPAIRED,
    HEALTH_GATED,
    HEALTH_MISSING,
    HEALTH_NONFINITE,
)
from uimm_jax.engine.uimm import build_diagnoser
from uimm_jax.errors import UIMMWarning
from uimm_jax.plants.base import LinearPlant, NonlinearPlant
from uimm_jax.plants.registry import get_plant, register_plant
from uimm_jax.scenario.measured import degrade_measurements
from uimm_jax.studies.imm_filter import LinearGaussianBank, imm_filter
from uimm_jax.studies.run import (
    filter_measurements,
    run_scenario,
    setup_scenario,
    simulate_scenario,
    summarize,
)

# --------------------------------------------------------------------------------------
# Validation of the Python API: every bad argument is named, with what is expected
# --------------------------------------------------------------------------------------

PROBLEM = make_linear_problem(0, M=3, n=2, m=1, p=1, N=20)


def call_imm(**changes):
    a = {**PROBLEM, **changes}
    bank = LinearGaussianBank(a["A"], a["B"], a["C"], a["Q"], a["R"])
    kw = {"gate": a["gate"]} if "gate" in a else {}
    return imm_filter(
        a.get("bank", bank),
        a["transition"],
        a["mu0"],
        a["x0"],
        a["P0"],
        a["inputs"],
        a["measurements"],
        **kw,
    )


NAN_A = np.where(np.ones_like(PROBLEM["A"]) > 0, np.nan, 0.0)
P_BAD_ROW = PROBLEM["transition"] * np.array([[1.0], [1.1], [1.0]])
P_NEG = np.array([[1.2, -0.2, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
P0_NONSYM = PROBLEM["P0"] + np.array([[0.0, 1.0], [0.0, 0.0]])

IMM_CASES = {
    "bank_not_a_bank": ({"bank": (1, 2, 3)}, TypeError, r"bank: expected a LinearGaussianBank"),
    "A_text": ({"A": "abc"}, ValueError, r"bank\.A: expected an array of numbers"),
    "A_shape": ({"A": np.zeros((3, 2, 3))}, ValueError, r"bank\.A: expected shape \(M, n, n\)"),
    "A_nan": ({"A": NAN_A}, ValueError, r"bank\.A: contains non-finite values"),
    "C_shape": ({"C": np.zeros((3, 1, 3))}, ValueError, r"bank\.C: expected shape \(3, m, 2\)"),
    "Q_not_psd": ({"Q": -PROBLEM["Q"]}, ValueError, r"bank\.Q\[0\]: not positive semi-definite"),
    "R_singular": ({"R": 0 * PROBLEM["R"]}, ValueError, r"bank\.R\[0\]: not positive definite"),
    "transition_rows": (
        {"transition": P_BAD_ROW},
        ValueError,
        r"transition: row 1 sums to 1\.\d+, not 1",
    ),
    "transition_negative": ({"transition": P_NEG}, ValueError, r"entry \[0, 1\] = -0\.2"),
    "transition_size": (
        {"transition": np.eye(2)},
        ValueError,
        r"transition: expected shape \(3, 3\) for 3 models",
    ),
    "mu0_negative": ({"mu0": [0.5, -0.1, 0.6]}, ValueError, r"initial_mode_probs: .* >= 0"),
    "mu0_length": ({"mu0": [0.5, 0.5]}, ValueError, r"initial_mode_probs: expected shape \(3,\)"),
    "x0_shape": ({"x0": np.zeros(5)}, ValueError, r"initial_mean: expected shape \(3, 2\)"),
    "P0_not_symmetric": ({"P0": P0_NONSYM}, ValueError, r"initial_cov\[0\]: not symmetric"),
    "inputs_rows": (
        {"inputs": PROBLEM["inputs"][:5]},
        ValueError,
        r"inputs: expected shape \(20, 1\)",
    ),
    "inputs_nan": ({"inputs": PROBLEM["inputs"] * np.nan}, ValueError, r"inputs: .*non-finite"),
    "measurements_width": (
        {"measurements": np.zeros((20, 4))},
        ValueError,
        r"measurements: expected shape \(\?, 1\)",
    ),
    "measurements_inf": (
        {"measurements": np.full((20, 1), np.inf)},
        ValueError,
        r"measurements: entry \(0, 0\) is inf; a missing measurement is NaN",
    ),
    "gate_negative": ({"gate": -1.0}, ValueError, r"gate: expected a finite number > 0"),
    "gate_nan": ({"gate": float("nan")}, ValueError, r"gate: expected a finite number > 0"),
    "gate_text": ({"gate": "big"}, ValueError, r"gate: expected None or a number > 0"),
}


@pytest.mark.parametrize("name", sorted(IMM_CASES))
def test_imm_filter_refuses_bad_arguments(name):
    changes, exc, pattern = IMM_CASES[name]
    with pytest.raises(exc, match=pattern):
        call_imm(**changes)


def test_fixed_up_values_warn():
    with pytest.warns(UIMMWarning, match=r"initial_mode_probs sum to 1\.2.*normalised"):
        res = call_imm(mu0=np.array([0.4, 0.4, 0.4]))
    np.testing.assert_allclose(res.mode_probs.sum(axis=1), 1.0, rtol=1e-12)


@pytest.fixture(scope="module")
def short():
    return short_scenario(1)


@pytest.fixture(scope="module")
def setup(short):
    return setup_scenario(short)


def test_scenario_entry_points_refuse_bad_arguments(short, setup):
    with pytest.raises(TypeError, match=r"scenario: expected a Scenario, got str; .*load_scenario"):
        setup_scenario("scenarios/paper_sim1_tuned.toml")
    with pytest.raises(TypeError, match=r"expected a Scenario, got dict; .*parse_scenario"):
        run_scenario({"name": "x"})
    with pytest.raises(
        ValueError, match=r"method: expected 'uimm', 'imm' or 'uimm-est', got 'ukf'"
    ):
        setup_scenario(short, "ukf")
    with pytest.raises(ValueError, match=r"magnitude_scale: expected a finite number > 0"):
        setup_scenario(short, magnitude_scale=float("nan"))
    with pytest.raises(ValueError, match=r"dtype: expected float32 or float64, got int32"):
        setup_scenario(short, dtype=jnp.int32)
    with pytest.raises(ValueError, match=r"seed: expected an integer in \[0, 4294967295\], got -1"):
        run_scenario(short, seed=-1)
    with pytest.raises(ValueError, match=r"chunk: expected an integer >= 1, got 0"):
        run_scenario(short, chunk=0)
    y = np.zeros((10, 3))
    with pytest.raises(ValueError, match=r"measurements: expected shape \(\?, 3\), got \(10, 2\)"):
        filter_measurements(setup, np.zeros((10, 2)))
    with pytest.raises(ValueError, match=r"measurements: no samples"):
        filter_measurements(setup, np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"inputs: expected shape \(10, 1\), got \(10, 2\)"):
        filter_measurements(setup, y, np.zeros((10, 2)))
    with pytest.raises(ValueError, match=r"inputs: entry \(3, 0\) is nan; inputs must be finite"):
        filter_measurements(setup, y, np.where(np.arange(10)[:, None] == 3, np.nan, 0.0))
    with pytest.raises(ValueError, match=r"measurements: entry \(0, 2\) is -inf"):
        filter_measurements(setup, np.where(np.arange(3) == 2, -np.inf, y))
    with pytest.raises(ValueError, match=r"chunk: expected an integer >= 1"):
        filter_measurements(setup, y, chunk=-5)
    with pytest.raises(ValueError, match=r"method: expected 'uimm' or 'imm', got 'x'"):
        build_diagnoser("x", setup.diagnoser.dyn, setup.table)
    with pytest.raises(ValueError, match=r"gate: expected a finite number > 0"):
        build_diagnoser("uimm", setup.diagnoser.dyn, setup.table, gate=-3)
    with pytest.raises(TypeError, match=r"table: expected a FaultTable"):
        build_diagnoser("uimm", setup.diagnoser.dyn, {"valve_wear": {"Kq": 3.0}})
    with pytest.raises(ValueError, match=r"faults \['a', 'b'\] all change parameter 'Kq'"):
        fault_table(("Kq",), np.ones(1), {"a": {"Kq": 2.0}, "b": {"Kq": 3.0}})


def linear_plant(**changes):
    kw = {
        "name": "robustness_test_plant",
        "state_names": ("x",),
        "input_names": ("u",),
        "output_names": ("y",),
        "param_names": ("k",),
        "nominal_values": (1.0,),
        "matrices": lambda p: (-p["k"] * jnp.eye(1), jnp.ones((1, 1)), jnp.eye(1), jnp.zeros(1)),
    }
    kw.update(changes)
    return LinearPlant(**kw)


PLANT_CASES = {
    "nominal_nan": ({"nominal_values": (float("nan"),)}, r"nominal value of 'k' is nan"),
    "nominal_text": ({"nominal_values": ("1",)}, r"nominal value of 'k' must be a number"),
    "no_states": ({"state_names": ()}, r"state_names is empty"),
    "names_string": ({"state_names": "xyz"}, r"state_names must be a tuple of strings.*\('x',\)"),
    "duplicate_outputs": ({"output_names": ("y", "y")}, r"output_names must be unique"),
    "empty_name": ({"name": ""}, r"plant name: expected a non-empty string"),
    "fault_unknown_param": (
        {"faults": (Fault("f", {"kk": 2.0}),)},
        r"fault 'f' names unknown parameter 'kk'",
    ),
    "fault_inf": (
        {"faults": (Fault("f", {"k": float("inf")}),)},
        r"fault 'f': value of 'k' is inf",
    ),
    "param_count": ({"nominal_values": (1.0, 2.0)}, r"param_names has 1 entries"),
    "time_kind": ({"time": "hybrid"}, r"time must be 'continuous' or 'discrete'"),
    "positive_unknown": (
        {"positive_params": ("zz",)},
        r"positive_params names unknown parameter 'zz'",
    ),
    "positive_nominal": (
        {"positive_params": ("k",), "nominal_values": (0.0,)},
        r"k is in positive_params but its nominal value is 0\.0",
    ),
    "positive_fault": (
        {"positive_params": ("k",), "faults": (Fault("f", {"k": -1.0}),)},
        r"fault 'f' sets k = -1\.0, but k is in positive_params",
    ),
}


@pytest.mark.parametrize("name", sorted(PLANT_CASES))
def test_bad_plant_definitions_are_refused(name):
    changes, pattern = PLANT_CASES[name]
    with pytest.raises(ValueError, match=pattern):
        linear_plant(**changes)


def test_plant_functions_are_checked_at_first_use(short):
    def wrong_shapes(p):
        return jnp.eye(2), jnp.zeros((2, 1)), jnp.eye(2), jnp.zeros(2)

    bad = linear_plant(name="robustness_bad_matrices", matrices=wrong_shapes)
    sc = dataclasses.replace(short, plant=bad, plant_params={}, faults={"f": {"k": 2.0}})
    with pytest.raises(ValueError, match=r"matrices\(p\) returned A of shape \(2, 2\); expected"):
        setup_scenario(sc)
    nl = NonlinearPlant(
        name="robustness_bad_nl",
        state_names=("x",),
        input_names=("u",),
        output_names=("y",),
        param_names=("k",),
        nominal_values=(1.0,),
        f=lambda x, u, p: x[0],  # a scalar, not (n,)
        h=lambda x, p: x,
    )
    with pytest.raises(ValueError, match=r"f\(x, u, p\) returned shape \(\); expected \(1,\)"):
        setup_scenario(dataclasses.replace(sc, plant=nl))
    with pytest.raises(TypeError, match="register_plant expects a LinearPlant"):
        register_plant("hydraulic_actuator")
    with pytest.raises(ValueError, match="already registered; pass overwrite=True"):
        register_plant(linear_plant(name="hydraulic_actuator"))
    with pytest.raises(ValueError, match=r"unknown plant model 'hydrolic'"):
        get_plant("hydrolic")


# --------------------------------------------------------------------------------------
# Numerical safety of the IMM kernel
# --------------------------------------------------------------------------------------


def check_outputs(res, M):
    """Finite outputs, normalised probabilities, symmetric PSD covariances."""
    for name in ("mode_probs", "mean", "cov", "model_loglik", "loglik_increments"):
        assert np.all(np.isfinite(np.asarray(getattr(res, name)))), name
    mu = np.asarray(res.mode_probs)
    assert mu.shape[1] == M and np.all(mu >= 0)
    np.testing.assert_allclose(mu.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    cov = np.asarray(res.cov)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), rtol=1e-12, atol=0)
    w = np.linalg.eigvalsh(cov)
    assert np.all(w >= -1e-9 * np.maximum(np.abs(w).max(axis=1, keepdims=True), 1e-300))


def test_absorbing_and_unreachable_modes_follow_the_reference():
    problem = make_linear_problem(5, M=3, n=2, m=1, p=1, N=200)
    # Mode 1 is absorbing; mode 2 can never be entered (zero column) and starts at 0.
    P = np.array([[0.9, 0.1, 0.0], [0.0, 1.0, 0.0], [0.05, 0.05, 0.9]])
    mu0 = np.array([0.6, 0.4, 0.0])
    problem = {**problem, "transition": P, "mu0": mu0}
    bank = LinearGaussianBank(*(problem[k] for k in ("A", "B", "C", "Q", "R")))
    res = imm_filter(
        bank, P, mu0, problem["x0"], problem["P0"], problem["inputs"], problem["measurements"]
    )
    check_outputs(res, 3)
    assert np.all(np.asarray(res.mode_probs)[:, 2] == 0.0)
    assert np.all(np.asarray(res.log_mode_probs)[:, 2] == -np.inf)
    ref = naive_imm(**problem)
    np.testing.assert_allclose(res.mode_probs, ref["mode_probs"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.mean, ref["mean"], rtol=1e-8, atol=1e-10)


def duplicated_sensor_problem(offset):
    """One state seen by two sensors with almost no noise: S is singular to rounding."""
    rng = np.random.default_rng(2)
    M, N = 2, 60
    x, ys = 0.0, []
    for k in range(N):
        x = 0.9 * x + 0.3 * rng.standard_normal()
        ys.append([x, x + (offset if k % 7 == 3 else 0.0)])
    bank = LinearGaussianBank(
        np.array([[[0.9]], [[0.5]]]),
        np.zeros((M, 1, 0)),
        np.ones((M, 2, 1)),
        np.full((M, 1, 1), 0.09),
        np.broadcast_to(1e-30 * np.eye(2), (M, 2, 2)),
    )
    P = np.array([[0.95, 0.05], [0.05, 0.95]])
    return bank, P, np.array(ys)


@pytest.mark.parametrize("offset", [0.0, 1.0])
def test_near_singular_innovation_covariance_is_repaired_and_flagged(offset):
    bank, P, y = duplicated_sensor_problem(offset)
    res = imm_filter(bank, P, [0.5, 0.5], np.zeros(1), np.eye(1), None, y)
    check_outputs(res, 2)
    health = np.asarray(res.health)
    assert np.any(health & HEALTH_COV_REPAIRED)
    if offset == 0.0:
        # Consistent sensors: the second one adds nothing, so the bank must behave as with
        # the first sensor alone (whose S is regular and never repaired).
        one = LinearGaussianBank(bank.A, bank.B, bank.C[:, :1], bank.Q, bank.R[:, :1, :1])
        ref = imm_filter(one, P, [0.5, 0.5], np.zeros(1), np.eye(1), None, y[:, :1])
        assert not np.any(np.asarray(ref.health) & HEALTH_COV_REPAIRED)
        np.testing.assert_allclose(res.mean, ref.mean, rtol=0, atol=1e-9)
        # (The mode probabilities are not compared: a repaired pivot adds log(pivot) to
        # each model's log-likelihood, which differs between models -- docs/robustness.md.)


@pytest.mark.parametrize("sigma", [1e6, 1e12])
def test_huge_outliers_without_gate_stay_finite_and_normalised(sigma):
    problem = make_linear_problem(7, M=3, n=2, m=2, p=1, N=100)
    y = problem["measurements"].copy()
    y[[10, 40, 41, 80], [0, 1, 0, 1]] += sigma
    bank = LinearGaussianBank(*(problem[k] for k in ("A", "B", "C", "Q", "R")))
    args = (problem["transition"], problem["mu0"], problem["x0"], problem["P0"])
    res = imm_filter(bank, *args, problem["inputs"], y)
    check_outputs(res, 3)
    # Ungated, an outlier is evidence like any other: the engine must still follow the
    # float64 reference (log-space probabilities; no likelihood clamp, no 0/0).
    ref = naive_imm(**{**problem, "measurements": y})
    np.testing.assert_allclose(res.mode_probs, ref["mode_probs"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.mean, ref["mean"], rtol=1e-6, atol=1e-6)
    gated = imm_filter(bank, *args, problem["inputs"], y, gate=100.0)
    check_outputs(gated, 3)
    flags = np.flatnonzero(np.asarray(gated.health) & HEALTH_GATED)
    np.testing.assert_array_equal(flags, [10, 40, 41, 80])
    # A gated step is predict-only: exactly the reference with those samples missing.
    y_missing = problem["measurements"].copy()
    y_missing[[10, 40, 41, 80]] = np.nan
    ref = naive_imm(**{**problem, "measurements": y_missing})
    np.testing.assert_allclose(gated.mode_probs, ref["mode_probs"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(gated.mean, ref["mean"], rtol=1e-8, atol=1e-10)


# --------------------------------------------------------------------------------------
# Numerical safety of the scenario diagnoser (tuned scenarios, gate = 100)
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def truth(setup):
    return simulate_scenario(setup, chunk=CHUNK)


def test_long_dropout_after_declarations(short, setup, truth):
    y = truth["y"].copy()
    y[7000:9500] = np.nan  # 0.25 s without any measurement, after both declarations
    _, out = filter_measurements(setup, y, truth["u"], chunk=CHUNK)
    assert all_finite(out)
    s = summarize(setup, truth["truth"], out, runtime_s=1.0)
    assert_declared_right(s, short)
    mu = out["mode_probs"]
    np.testing.assert_allclose(mu.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    assert np.all(out["health"][7000:9500] & HEALTH_MISSING)
    # Declared faults stay declared; after the dropout the filter re-acquires without
    # gating the returning measurements.
    assert np.all(out["declared"][7000:] == out["declared"][6999])
    assert s["health"]["gated_steps"] == 0
    assert out["recognised"][-1] == truth["truth"][-1]


def test_all_zero_inputs_and_huge_inputs(short, setup, truth):
    zero = short_scenario(1, input__amplitude=0.0)
    truth0 = simulate_scenario(setup_scenario(zero), chunk=CHUNK)
    assert np.all(truth0["u"] == 0.0)
    _, out = filter_measurements(setup_scenario(zero), truth0["y"], truth0["u"], chunk=CHUNK)
    assert all_finite(out)
    np.testing.assert_allclose(out["mode_probs"].sum(axis=1), 1.0, rtol=0, atol=1e-12)
    # Inputs of 1e30 against measurements of a normal run: the predictions run away (to
    # ~1e32 Pa or beyond), most samples are flagged (gated as outliers, or non-finite
    # values caught and replaced: which one depends on the hypotheses' magnitudes; with
    # session 9's race_floor the latter), and nothing overflows into the outputs.
    huge = np.full_like(truth["u"], 1e30)
    _, out = filter_measurements(setup, truth["y"], huge, chunk=CHUNK)
    assert all_finite(out)
    assert np.mean(out["health"] & (HEALTH_GATED | HEALTH_NONFINITE) > 0) > 0.5
    np.testing.assert_allclose(out["mode_probs"].sum(axis=1), 1.0, rtol=0, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("sim", [1, 2])
def test_dropouts_and_1e6_sigma_outliers_2e5_steps(sim):
    """The acceptance study on 2e5 steps (the 1e6-step version: benchmarks/robustness_long.py)."""
    sc = short_scenario(sim, duration=20.0, events=(6.0, 12.0))
    setup = setup_scenario(sc)
    tr = simulate_scenario(setup, chunk=CHUNK)
    y, info = degrade_measurements(tr["y"], sc.measurement_noise, seed=sim)
    _, out = filter_measurements(setup, y, tr["u"], chunk=CHUNK)
    assert all_finite(out)
    np.testing.assert_allclose(out["mode_probs"].sum(axis=1), 1.0, rtol=0, atol=1e-12)
    s = summarize(setup, tr["truth"], out, runtime_s=1.0)
    assert_declared_right(s, sc)
    assert max(s["detection_delay_s"].values()) < 0.2
    steps = info["outliers"][:, 0]
    assert np.all(out["health"][steps] & HEALTH_GATED)  # every outlier is gated ...
    assert s["health"]["gated_steps"] <= len(set(steps.tolist())) + 5  # ... and little else
    assert s["health"]["nonfinite_caught_steps"] == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        clean = filter_measurements(setup, tr["y"], tr["u"], chunk=CHUNK)[1]
    s_clean = summarize(setup, tr["truth"], clean, runtime_s=1.0)
    for fault, delay in s["detection_delay_s"].items():
        assert abs(delay - s_clean["detection_delay_s"][fault]) < 0.05, (fault, delay)
    assert s["health"]["missing_steps"] == int(np.isnan(y).any(axis=1).sum())
