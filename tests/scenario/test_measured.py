"""Measured data: file layouts, their errors, and missing measurements in the filter."""

from __future__ import annotations

import json
import re
import warnings

import numpy as np
import pytest

from _engine_helpers import run_imm_filter
from _reference import make_linear_problem, naive_imm
from _robustness_helpers import CHUNK, short_scenario, write_short
from uimm_jax import cli
from uimm_jax.engine.imm import HEALTH_MISSING
from uimm_jax.errors import UIMMWarning
from uimm_jax.scenario.measured import (
    MeasuredData,
    MeasurementError,
    degrade_measurements,
    load_measurements,
    measured_data,
)
from uimm_jax.studies.run import (
    filter_measurements,
    run_scenario,
    setup_scenario,
    simulate_scenario,
)
from uimm_jax.studies.truth import scenario_inputs


@pytest.fixture(scope="module")
def sc():
    return short_scenario(1)


@pytest.fixture(scope="module")
def sim(sc):
    """The short scenario's simulated truth (float64)."""
    return simulate_scenario(setup_scenario(sc), chunk=CHUNK)


def write_csv(path, header, rows, comments=()):
    lines = [f"# {c}" for c in comments] + [",".join(header)]
    lines += [",".join(r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def fmt(v):
    return "" if np.isnan(v) else repr(float(v))


# --------------------------------------------------------------------------------------
# Layouts
# --------------------------------------------------------------------------------------


def test_csv_any_column_order_with_times_inputs_and_missing_cells(tmp_path, sc):
    rng = np.random.default_rng(0)
    N = 7
    y = rng.standard_normal((N, 3))
    y[1, 0] = y[4, :] = np.nan  # one missing channel, one all-missing sample
    u = rng.standard_normal((N, 1))
    t = (np.arange(N) + 1) * sc.dt
    header = ["p_h", "i_v", "t", "x_p", "v_p"]
    rows = [
        [fmt(y[k, 2]), fmt(u[k, 0]), repr(float(t[k])), fmt(y[k, 0]), fmt(y[k, 1])]
        for k in range(N)
    ]
    rows[4][0] = "NaN"  # "nan" in any case is missing too
    path = write_csv(tmp_path / "data.csv", header, rows, comments=["exported by a test"])
    with pytest.warns(UIMMWarning, match="7 samples, the scenario has 10000"):
        data = load_measurements(path, sc)
    assert isinstance(data, MeasuredData) and data.source == str(path)
    np.testing.assert_array_equal(data.y, y)  # NaN positions included
    np.testing.assert_array_equal(data.u, u)
    np.testing.assert_array_equal(data.t, t)
    np.testing.assert_array_equal(np.asarray(data), y)
    assert data.num_steps == N and data.missing_fraction == pytest.approx(4 / 21)


def test_csv_outputs_only_and_npy_and_npz_give_the_same_data(tmp_path, sc, sim):
    y = sim["y"].copy()
    y[::97, 1] = np.nan
    rows = [[fmt(v) for v in row] for row in y]
    csv_data = load_measurements(write_csv(tmp_path / "y.csv", ["x_p", "v_p", "p_h"], rows), sc)
    np.save(tmp_path / "y.npy", y)
    npy_data = load_measurements(tmp_path / "y.npy", sc)
    np.savez(tmp_path / "y.npz", y=y, u=sim["u"], t=sim["t"])
    npz_data = load_measurements(tmp_path / "y.npz", sc)
    for data in (csv_data, npy_data, npz_data):
        np.testing.assert_array_equal(data.y, y)  # repr round trip is exact
    assert csv_data.u is None and npy_data.u is None
    np.testing.assert_array_equal(npz_data.u, sim["u"])


CSV_ERRORS = {
    # name: (header, rows, regex on the message)
    "no_header": (["1.0", "2.0", "3.0"], [["1", "2", "3"]], r"line 1 \(header\).*header naming"),
    "semicolons": (["x_p;v_p;p_h"], [["1;2;3"]], r"separated by commas"),
    "unknown_column": (["x_p", "v_p", "p_hh"], [], r"unknown column 'p_hh'.*did you mean 'p_h'"),
    "duplicate": (["x_p", "v_p", "p_h", "x_p"], [], r"'x_p' appears twice"),
    "missing_output": (["x_p", "p_h"], [["1", "2"]], r"missing output column\(s\) v_p"),
    "unnamed_column": (["x_p", "", "p_h"], [], r"column 2 has no name"),
    "no_rows": (["x_p", "v_p", "p_h"], [], r"no data rows"),
    "ragged": (["x_p", "v_p", "p_h"], [["1", "2"]], r"line 2: 2 cells, the header has 3"),
    "text_cell": (["x_p", "v_p", "p_h"], [["1", "abc", "3"]], r"line 2, column 'v_p'.*'abc'"),
    "inf_cell": (["x_p", "v_p", "p_h"], [["1", "inf", "3"]], r"column 'v_p'.*infinite.*empty"),
    "missing_input": (
        ["x_p", "v_p", "p_h", "i_v"],
        [["1", "2", "3", ""]],
        r"line 2, column 'i_v'.*inputs may not be missing",
    ),
    "times_from_zero": (
        ["t", "x_p", "v_p", "p_h"],
        [["0.0", "1", "2", "3"]],
        r"line 2, column 't'.*\(k \+ 1\) dt.*start at 0",
    ),
    "times_wrong_step": (
        ["t", "x_p", "v_p", "p_h"],
        [["0.0001", "1", "2", "3"], ["0.0003", "1", "2", "3"]],
        r"line 3, column 't'.*sample 1 must be at",
    ),
    "missing_time": (
        ["t", "x_p", "v_p", "p_h"],
        [["", "1", "2", "3"]],
        r"line 2.*time nan is not a finite number",
    ),
}


@pytest.mark.parametrize("name", sorted(CSV_ERRORS))
def test_malformed_csv_is_refused_with_line_and_column(tmp_path, sc, name):
    header, rows, pattern = CSV_ERRORS[name]
    path = write_csv(tmp_path / f"{name}.csv", header, rows)
    with pytest.raises(MeasurementError) as e:
        load_measurements(path, sc)
    msg = str(e.value)
    assert msg.startswith(f"{path}: "), msg
    assert re.search(pattern, msg, re.IGNORECASE), msg


def test_other_file_errors(tmp_path, sc):
    with pytest.raises(MeasurementError, match="file not found"):
        load_measurements(tmp_path / "nothing.csv", sc)
    (tmp_path / "d.txt").write_text("x_p,v_p,p_h\n1,2,3\n")
    with pytest.raises(MeasurementError, match=r"unknown file type '\.txt'.*\.csv, \.npy or \.npz"):
        load_measurements(tmp_path / "d.txt", sc)
    (tmp_path / "empty.csv").write_text("# only a comment\n\n")
    with pytest.raises(MeasurementError, match="empty file"):
        load_measurements(tmp_path / "empty.csv", sc)
    (tmp_path / "latin.csv").write_bytes("x_p,v_p,p_h\n1,2,\xe9\n".encode("latin-1"))
    with pytest.raises(MeasurementError, match="not UTF-8"):
        load_measurements(tmp_path / "latin.csv", sc)
    np.save(tmp_path / "wide.npy", np.zeros((5, 4)))
    with pytest.raises(MeasurementError, match=r"expected shape \(N, 3\).*got \(5, 4\)"):
        load_measurements(tmp_path / "wide.npy", sc)
    np.save(tmp_path / "cplx.npy", np.zeros((5, 3), complex))
    with pytest.raises(MeasurementError, match="real numbers, got dtype complex"):
        load_measurements(tmp_path / "cplx.npy", sc)
    np.save(tmp_path / "inf.npy", np.array([[0.0, np.inf, 0.0]]))
    with pytest.raises(MeasurementError, match=r"sample 0, output 'v_p' is inf"):
        load_measurements(tmp_path / "inf.npy", sc)
    (tmp_path / "bad.npy").write_bytes(b"not an array")
    with pytest.raises(MeasurementError, match="not a readable .npy"):
        load_measurements(tmp_path / "bad.npy", sc)
    np.savez(tmp_path / "z.npz", y=np.zeros((2, 3)), v=np.zeros(2))
    with pytest.raises(MeasurementError, match=r"unknown array\(s\) \['v'\]"):
        load_measurements(tmp_path / "z.npz", sc)
    np.savez(tmp_path / "u.npz", y=np.zeros((2, 3)), u=np.zeros((3, 1)))
    with pytest.raises(MeasurementError, match=r"inputs: expected shape \(2, 1\)"):
        load_measurements(tmp_path / "u.npz", sc)
    with pytest.raises(TypeError, match="expected a uimm_jax.Scenario"):
        load_measurements(tmp_path / "wide.npy", "scenarios/paper_sim1.toml")


# --------------------------------------------------------------------------------------
# Missing measurements in the IMM: against the naive reference
# --------------------------------------------------------------------------------------


def run_engine(problem, y):
    return run_imm_filter(problem, y, return_model_means=True)


@pytest.mark.parametrize("seed", [0, 1])
def test_missing_single_channels_follow_the_naive_reference(seed):
    problem = make_linear_problem(seed, M=3, n=3, m=3, p=1, N=120)
    rng = np.random.default_rng(seed + 10)
    y = problem["measurements"].copy()
    y[rng.random(y.shape) < 0.25] = np.nan  # single channels (and some whole samples)
    assert np.any(np.isnan(y).sum(axis=1) == 1) and np.any(np.isnan(y).sum(axis=1) == 2)
    ref = naive_imm(**{**problem, "measurements": y})
    res = run_engine(problem, y)
    np.testing.assert_allclose(res.mode_probs, ref["mode_probs"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.mean, ref["mean"], rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.cov, ref["cov"], rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.model_mean, ref["model_mean"], rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.model_loglik, ref["model_loglik"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.marginal_loglik, ref["marginal_loglik"], rtol=1e-10)
    missing = np.any(np.isnan(y), axis=1)
    np.testing.assert_array_equal(np.asarray(res.health) & HEALTH_MISSING > 0, missing)


def test_all_missing_steps_follow_the_markov_prediction():
    problem = make_linear_problem(3, M=3, n=2, m=2, p=1, N=120)
    y = problem["measurements"].copy()
    y[40:70] = np.nan  # a long dropout of every channel
    res = run_engine(problem, y)
    ref = naive_imm(**{**problem, "measurements": y})
    mu = np.asarray(res.mode_probs)
    P = problem["transition"]
    for k in range(40, 70):
        np.testing.assert_allclose(mu[k], mu[k - 1] @ P, rtol=1e-12, atol=1e-15)
        np.testing.assert_array_equal(res.model_loglik[k], 0.0)
    np.testing.assert_allclose(mu, ref["mode_probs"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.mean, ref["mean"], rtol=1e-8, atol=1e-10)
    # Predict-only: the uncertainty at the end of the dropout exceeds the filtered one.
    tr = np.trace(np.asarray(res.cov), axis1=1, axis2=2)
    assert tr[69] > 1.2 * tr[39]


# --------------------------------------------------------------------------------------
# Missing measurements in the scenario diagnoser
# --------------------------------------------------------------------------------------


def test_diagnoser_dropout_follows_the_markov_prediction(sc, sim):
    setup = setup_scenario(sc)
    y = sim["y"].copy()
    y[1000:1500] = np.nan  # before the first fault (0.3 s): no declaration in flight
    y[2000:2600, 2] = np.nan  # pressure channel only
    _, out = filter_measurements(setup, y, sim["u"], chunk=CHUNK)
    mu = out["mode_probs"]
    P = setup.transition
    for k in range(1000, 1500):
        np.testing.assert_allclose(mu[k], mu[k - 1] @ P, rtol=1e-11, atol=1e-300)
    assert np.all(out["declared"][:3000] == 0)
    health = out["health"]
    np.testing.assert_array_equal(health & HEALTH_MISSING > 0, np.isnan(y).any(axis=1))
    assert np.all(np.isfinite(mu)) and np.all(np.isfinite(out["mean"]))


def test_file_inputs_are_used_and_the_truth_follows_the_events(tmp_path, sc, sim):
    y = sim["y"]
    u_file = 0.5 * sim["u"] + 0.001  # not the scenario's input signal
    np.savez(tmp_path / "m.npz", y=y, u=u_file)
    data = load_measurements(tmp_path / "m.npz", sc)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = run_scenario(sc, measurements=data, chunk=CHUNK)
    _, ref = filter_measurements(setup_scenario(sc), y, u_file, chunk=CHUNK)
    for k in ("mode_probs", "mean", "declared", "health"):
        np.testing.assert_array_equal(res.outputs[k], ref[k], err_msg=k)
    np.testing.assert_array_equal(res.truth["u"], u_file)
    np.testing.assert_array_equal(res.truth["truth"], sim["truth"])  # from the events
    assert np.all(np.isnan(res.truth["x"]))
    # Without inputs in the data the scenario's signal is used: different results.
    res_default = run_scenario(sc, measurements=y, chunk=CHUNK)
    np.testing.assert_array_equal(res_default.truth["u"], scenario_inputs(sc, y.shape[0]))
    assert not np.array_equal(res_default.outputs["mean"], res.outputs["mean"])


def test_measured_data_validation(sc):
    with pytest.raises(MeasurementError, match=r"<array>: measurements: expected shape \(N, 3\)"):
        measured_data(sc, np.zeros((4, 2)))
    with pytest.raises(MeasurementError, match=r"no samples"):
        measured_data(sc, np.zeros((0, 3)))
    with pytest.raises(MeasurementError, match=r"input 'i_v' is nan"):
        measured_data(sc, np.zeros((2, 3)), u=[0.0, np.nan])
    with pytest.raises(MeasurementError, match=r"t\[1\].*sample 1 must be at"):
        measured_data(sc, np.zeros((2, 3)), t=[sc.dt, 3 * sc.dt])
    data = measured_data(sc, np.zeros((2, 3)), u=[1.0, 2.0], t=[sc.dt, 2 * sc.dt])
    assert data.u.shape == (2, 1)


def test_degrade_measurements_is_reproducible(sim, sc):
    y2, info = degrade_measurements(sim["y"], sc.measurement_noise, seed=4)
    y3, _ = degrade_measurements(sim["y"], sc.measurement_noise, seed=4)
    np.testing.assert_array_equal(y2, y3)
    assert abs(info["dropped"].mean() - 0.1) < 0.01
    assert np.array_equal(np.isnan(y2), info["dropped"])
    k, c = info["outliers"].T
    sigma = np.sqrt(np.diag(sc.measurement_noise))[c]
    np.testing.assert_allclose(np.abs(y2[k, c] - sim["y"][k, c]), 1e6 * sigma, rtol=1e-6)
    assert len({(a, b) for a, b in info["outliers"]}) == 100


# --------------------------------------------------------------------------------------
# CLI: uimm-jax run SCENARIO --measurements FILE (in process, compiled code reused)
# --------------------------------------------------------------------------------------


def test_cli_measurements_end_to_end(tmp_path, sc, sim, monkeypatch, capsys):
    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)  # main() replaces it
    scen = write_short(tmp_path / "short.toml", 1)
    y = sim["y"].copy()
    y[::50, 0] = np.nan
    header = ["t", "x_p", "v_p", "p_h", "i_v"]
    rows = [
        [repr(float(t)), *(fmt(v) for v in yy), repr(float(uu[0]))]
        for t, yy, uu in zip(sim["t"], y, sim["u"], strict=True)
    ]
    data_path = write_csv(tmp_path / "measured.csv", header, rows)
    out = tmp_path / "out"
    argv = ["run", str(scen), "--measurements", str(data_path), "--out", str(out), "--quiet"]
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err and "error" not in captured.err
    summary = json.loads((out / "summary.json").read_text())
    assert (out / "states.png").is_file()  # figures work with unknown true states
    api = run_scenario(sc, measurements=load_measurements(data_path, sc), chunk=CHUNK).summary
    for key in ("declarations", "detection_delay_s", "mode_accuracy", "health", "num_steps"):
        assert summary[key] == api[key], key
    assert summary["health"]["missing_steps"] == int(np.isnan(y).any(axis=1).sum())
    assert [d["fault"] for d in summary["declarations"]] == ["valve_wear", "leakage"]
    # Recorded data with missing channels: the innovation check counts every step that
    # observed a channel, per observed channel, and finds the noise the data's.
    ic = summary["innovation_check"]
    assert ic == api["innovation_check"] and ic["samples"] == len(y)
    assert ic["verdict"] == "consistent" and 0.8 < ic["mean_nis_per_channel"] < 1.25
    # Per output: the one with gaps counts only its observed samples.
    seen = {name: int(np.isfinite(y[:, i]).sum()) for i, name in enumerate(header[1:4])}
    assert {k: v["samples"] for k, v in ic["by_channel"].items()} == seen
    assert all(v["verdict"] == "consistent" for v in ic["by_channel"].values())
    assert ic["unexplained"] == []  # gaps do not make innovations look unexplained
