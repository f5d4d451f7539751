"""Bad input found by probing (session 4): each is refused with a named field, or warned about.

Every case here used to crash deep inside NumPy, JAX or matplotlib, run without limit, or
silently produce NaN or a changed value.  The scenario-file cases live in the malformed
corpus (``tests/malformed``, ``test_scenarios.py``); these are the rest.
"""

from __future__ import annotations

import re
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import uimm_jax
from _reference import make_linear_problem
from _robustness_helpers import short_dict, short_scenario
from uimm_jax import cli
from uimm_jax._checks import MAX_SEED, check_seed, check_stochastic
from uimm_jax.engine.dynamics import MAX_SQUARINGS
from uimm_jax.errors import UIMMWarning
from uimm_jax.plants.base import LinearPlant
from uimm_jax.plants.dynamics import make_dynamics
from uimm_jax.plants.hydraulic_actuator import HYDRAULIC_ACTUATOR
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import dump_scenario
from uimm_jax.studies import plots as plotting
from uimm_jax.studies.run import run_scenario


def _filter(problem, **changes):
    p = {**problem, **changes}
    bank = uimm_jax.LinearGaussianBank(p["A"], p["B"], p["C"], p["Q"], p["R"])
    return uimm_jax.imm_filter(
        bank, p["transition"], p["mu0"], p["x0"], p["P0"], p["inputs"], p["measurements"]
    )


@pytest.fixture(scope="module")
def problem():
    return make_linear_problem(0, N=20)


# --------------------------------------------------------------------------------------
# Python API
# --------------------------------------------------------------------------------------


def test_seed_beyond_32_bits_is_refused():
    # jax.random.PRNGKey(2**40) is [0, 0] without x64: it would alias seed 0.
    assert check_seed(MAX_SEED) == MAX_SEED
    with pytest.raises(ValueError, match=r"seed: expected an integer in \[0, 4294967295\]"):
        check_seed(MAX_SEED + 1)
    with pytest.raises(ValueError, match=r"^seed: .*got 4294967296"):
        run_scenario(short_scenario(duration=0.01, events=(0.002, 0.004)), seed=2**32)


def test_float32_transition_matrix_is_accepted_unchanged():
    p32 = np.array([[0.95, 0.05], [0.05, 0.95]], np.float32)
    assert abs(p32.astype(np.float64).sum(axis=1)[0] - 1.0) > 1e-9  # beyond the float64 bound
    np.testing.assert_array_equal(check_stochastic(p32), p32.astype(np.float64))
    with pytest.raises(ValueError, match="row 0 sums to"):
        check_stochastic(np.array([[0.95, 0.0501], [0.05, 0.95]], np.float32))
    with pytest.raises(ValueError, match="row 0 sums to"):
        check_stochastic(np.array([[0.95, 0.05 + 1e-8], [0.05, 0.95]]))  # float64: 1e-9


def test_imm_filter_refuses_empty_and_complex_input(problem):
    with pytest.raises(ValueError, match=r"^measurements: no samples"):
        _filter(problem, measurements=problem["measurements"][:0], inputs=problem["inputs"][:0])
    with pytest.raises(ValueError, match=r"^bank\.A: .* no models"):
        _filter(problem, A=problem["A"][:0])
    with pytest.raises(ValueError, match=r"^measurements: expected real numbers"):
        _filter(problem, measurements=problem["measurements"].astype(complex))
    with pytest.raises(ValueError, match=r"^initial_mode_probs: entries sum to inf \(overflow\)"):
        _filter(problem, mu0=np.full(len(problem["mu0"]), 1e308))


def test_load_scenario_names_a_wrong_argument_type():
    with pytest.raises(TypeError, match=r"load_scenario: path: expected the path .* NoneType"):
        load_scenario(None)


def test_byte_order_mark_is_tolerated(tmp_path):
    src = tmp_path / "plain.toml"
    dump_scenario(short_dict(duration=0.01, events=(0.002, 0.004)), src)
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbf" + src.read_bytes())
    assert load_scenario(bom).name == load_scenario(src).name


# --------------------------------------------------------------------------------------
# Warnings: accepted, unchanged, but the user is told
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "changes, field, pattern",
    [
        ({"input__frequency": 5000.0}, r"\[input\]\.frequency", "Nyquist"),
        (
            {"input": {"kind": "step", "amplitude": 0.01, "step_time": 5.0}},
            r"\[input\]\.step_time",
            "never happens",
        ),
    ],
)
def test_inputs_the_samples_cannot_show_warn(changes, field, pattern):
    d = short_dict(duration=1.0, **changes)
    d["dt"] = 1e-4
    with pytest.warns(UIMMWarning, match=field + ".*" + pattern):
        parse_scenario(d)


def test_two_faults_on_one_sample_warn():
    with pytest.warns(UIMMWarning, match=r"\[\[events\]\]\[1\]\.time: .*same sample"):
        short_scenario(duration=0.01, events=(0.005, 0.005))


# --------------------------------------------------------------------------------------
# Plants whose parameters make no sense
# --------------------------------------------------------------------------------------


def test_absurdly_fast_dynamics_are_refused_before_compiling():
    theta = HYDRAULIC_ACTUATOR.theta({"Kh": 1e300})
    with pytest.raises(ValueError, match=rf"Kh = 1e\+300.*at most {MAX_SQUARINGS} are allowed"):
        make_dynamics(HYDRAULIC_ACTUATOR, 1e-4, theta[None])
    make_dynamics(HYDRAULIC_ACTUATOR, 1e-4, HYDRAULIC_ACTUATOR.theta()[None])  # nominal is fine


def test_non_finite_matrices_of_a_user_plant_are_refused():
    plant = LinearPlant(
        name="mass_on_spring_test",
        state_names=("x", "v"),
        input_names=("f",),
        output_names=("x",),
        param_names=("m", "k"),
        nominal_values=(1.0, 4.0),
        matrices=lambda p: (
            jnp.array([[0.0, 1.0], [-p["k"] / p["m"], 0.0]]),
            jnp.array([[0.0], [1.0 / p["m"]]]),
            jnp.array([[1.0, 0.0]]),
            jnp.zeros(1),
        ),
    )
    with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        with pytest.raises(ValueError, match=r"non-finite entry for the parameters m = 0\.0"):
            make_dynamics(plant, 0.01, plant.theta({"m": 0.0})[None])


def test_the_actuator_declares_its_positive_params():
    # The positive_params mechanism itself: PLANT_CASES in test_robustness.py.
    assert {"mh", "Vh", "Eh"} <= set(HYDRAULIC_ACTUATOR.positive_params)


def test_a_diverging_truth_is_an_error_not_missing_data():
    # Kq and Kc may grow without bound (no positivity limit), but 1e300 times the
    # valve-wear deviation overflows the fault phase's discretised dynamics.
    d = short_dict(duration=0.01, events=(0.002, 0.004))
    d["events"][0]["magnitude"] = 1e300
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        with pytest.raises(ValueError, match=r"dynamics are not finite after valve_wear"):
            run_scenario(parse_scenario(d))
    # A negative damping (Bh may be zero, so it is not a positive parameter) makes the
    # plant unstable: finite matrices, but the simulated truth overflows after ~0.04 s.
    d = short_dict(duration=0.1, events=(0.02, 0.04))
    d["plant"]["params"] = {"Bh": -1e6}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        with pytest.raises(ValueError, match=r"simulated truth is not finite from t = 0\.0"):
            run_scenario(parse_scenario(d))


def test_large_magnitudes_of_a_positive_parameter_stay_positive_on_the_log_scale():
    from uimm_jax.scenario.sweep import sweep_spec
    from uimm_jax.studies.run import setup_scenario

    sc = short_scenario(sim=2, duration=0.01, events=(0.002, 0.004))  # air in oil: Eh drops
    sweep_spec(sc, runs=2, magnitudes=[1.0, 2.0, 3.0])  # linear: 6e6 - 2 * 5.4e6 < 0
    table = setup_scenario(sc).table
    q = sc.plant.param_names.index("Eh")
    j = table.names.index("air_in_oil")
    for a in (0.5, 1.0, 2.0, 3.0):
        th = table.theta_numpy(np.eye(3, dtype=bool)[j], np.full(3, a))
        assert th[q] == pytest.approx(6e6 * 0.1**a, rel=1e-12)


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------


def test_cli_checks_out_and_flags_before_running(tmp_path, capsys):
    f = dump_scenario(short_dict(duration=0.01, events=(0.002, 0.004)), tmp_path / "s.toml")
    (tmp_path / "afile").write_text("x")
    cases = [
        (["run", f, "--out", tmp_path / "afile" / "sub"], r"--out: cannot create"),
        (["sweep", f, "--out", tmp_path / "afile"], r"--out: .* is a file"),
        (["sweep", f, "--host-devices", "0"], r"--host-devices: expected an integer >= 1"),
        (["sweep", f, "--runs", "0"], r"^error: --runs: expected an integer >= 1, got 0$"),
        (["sweep", f, "--seed", str(2**32)], r"--seed: expected an integer in \[0, 4294967295\]"),
    ]
    for args, pattern in cases:
        assert cli.main([str(a) for a in args] + ["--quiet", "--no-plots"]) == 2, args
        err = capsys.readouterr().err.strip()
        assert "Traceback" not in err and len(err.splitlines()) == 1, err
        assert re.search(pattern, err), (pattern, err)
    with pytest.raises(SystemExit):  # argparse: an empty item is not silently dropped
        cli.main(["sweep", str(f), "--magnitudes", "1,,2"])
    assert "argument --magnitudes: empty item in '1,,2'" in capsys.readouterr().err


def test_mode_probability_plot_ignores_markers_outside_the_data(tmp_path):
    # Three samples of measured data against a scenario with onsets at 30 s and 60 s used
    # to overflow matplotlib's text rasteriser.
    t = np.array([1e-4, 2e-4, 3e-4])
    probs = np.full((3, 2), 0.5)
    fig = plotting.plot_mode_probabilities(
        t, probs, ["a", "b"], events=[(30.0, "b")], declarations=[(60.0, "b")]
    )
    plotting.save_figure(fig, tmp_path / "p.png")
    assert fig.axes[0].get_xlim()[1] < 1.0  # the axis spans the data, not the markers


def test_measurement_array_errors_name_the_argument_once():
    sc = short_scenario(duration=0.01, events=(0.002, 0.004))
    with pytest.raises(ValueError, match=r"^measurements: expected shape \(N, 3\)"):
        run_scenario(sc, measurements=np.zeros((5, 2)))


def test_one_sample_plots_do_not_warn(tmp_path):
    t = np.array([1e-3])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fig = plotting.plot_mode_probabilities(t, np.full((1, 2), 0.5), ["a", "b"])
        plotting.save_figure(fig, tmp_path / "p.png")
        fig = plotting.plot_mode_recognition(t, np.zeros(1, int), np.zeros(1, int), ["f"])
        plotting.save_figure(fig, tmp_path / "r.png")


def test_sweep_with_an_overflowing_truth_is_refused():
    from uimm_jax.studies.sweep import run_sweep

    sc = short_scenario(duration=0.01, events=(0.002, 0.004))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        with pytest.raises(ValueError, match=r"\[sweep\]: the truth's discretised dynamics .*Kq"):
            run_sweep(sc, runs=1, magnitudes=[1e300], fault_free=False, progress=False)
