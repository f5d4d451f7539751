"""float32 mode (uimm_jax.studies.float32): exact scaling, and agreement with float64.

The 1e6-step comparison on the shipped paper scenarios (with the speed-up) is
``benchmarks/float32_agreement.py``; here the tuned scenarios run for 1 s.
"""

from __future__ import annotations

import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from _robustness_helpers import CHUNK, all_finite, short_dict, short_scenario, write_short
from uimm_jax import cli
from uimm_jax.engine.imm import HEALTH_COV_REPAIRED
from uimm_jax.errors import UIMMWarning
from uimm_jax.scenario.parse import parse_scenario
from uimm_jax.studies.float32 import (
    RESOLUTION_LIMIT,
    Scaling,
    _warn_if_unresolvable,
    choose_scaling,
    float32_agreement,
    run_scenario_float32,
    scale_scenario,
    scaled_plant,
)
from uimm_jax.studies.run import filter_measurements, run_scenario, setup_scenario, summarize

#: Stated tolerance on declaration times, float32 vs float64 (docs/robustness.md).
DECLARATION_TOLERANCE_S = 1e-3
#: Stated tolerance on the mean absolute mode-probability difference, per method
#: (docs/robustness.md: uimm-est measured 7e-5 on sim 1 and 1.4e-3 on sim 2).
MODE_PROB_TOLERANCE = {"uimm": 1e-3, "uimm-est": 3e-3}
#: Stated tolerance on the declared magnitudes' relative difference (uimm-est).
MAGNITUDE_TOLERANCE = 1e-2


def test_scaling_is_an_exact_similarity_transform():
    sc = short_scenario(1)
    scaling = choose_scaling(sc)
    S, T = scaling.S, scaling.T
    for v in (S, T):  # powers of two: scaling adds no rounding of its own
        np.testing.assert_array_equal(np.exp2(np.round(np.log2(v))), v)
    plant = sc.plant
    scaled = scaled_plant(plant, scaling)
    assert scaled is scaled_plant(plant, scaling)  # cached: the compiled filter is reused
    theta = jnp.asarray(plant.theta(sc.plant_params))
    A, B, C, d = (np.asarray(a) for a in plant.matrices(plant.params(theta)))
    As, Bs, Cs, ds = (np.asarray(a) for a in scaled.matrices(scaled.params(theta)))
    np.testing.assert_array_equal(As, np.diag(1 / S) @ A @ np.diag(S))
    np.testing.assert_array_equal(Bs, np.diag(1 / S) @ B)
    np.testing.assert_array_equal(Cs, np.diag(1 / T) @ C @ np.diag(S))
    np.testing.assert_array_equal(ds, d / T)
    ssc, _ = scale_scenario(sc, scaling)
    np.testing.assert_array_equal(
        ssc.process_noise, np.diag(1 / S) @ sc.process_noise @ np.diag(1 / S)
    )
    np.testing.assert_array_equal(
        ssc.measurement_noise, np.diag(1 / T) @ sc.measurement_noise @ np.diag(1 / T)
    )
    # In scaled units the steady-state covariance and R are O(1): scaling them again
    # asks for factors of 1/2, 1 or 2 only.
    again = choose_scaling(ssc)
    assert set(again.state) | set(again.output) <= {0.5, 1.0, 2.0}, again
    with pytest.raises(ValueError, match="finite positive scales"):
        Scaling((1.0, 0.0, 1.0), (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="expected 3 state scales"):
        scaled_plant(plant, Scaling((1.0,), (1.0, 1.0, 1.0)))


def test_resolution_warning_and_x64_requirement():
    R = np.diag([1e-24, 1.0])
    y = np.array([[1e-3, 5.0], [np.nan, 1.0]])  # 1e-3 m against sigma 1e-12 m
    with pytest.warns(UIMMWarning, match=r"channel 0 reaches 1e\+09 noise sigmas"):
        _warn_if_unresolvable(y, R)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _warn_if_unresolvable(np.array([[2.0**24 * RESOLUTION_LIMIT, 1.0]]), np.eye(2))
    with jax.enable_x64(False), pytest.raises(RuntimeError, match="enable float64"):
        run_scenario_float32(short_scenario(1))


@pytest.fixture(scope="module")
def pair():
    """float64 and float32 runs of both short tuned scenarios on the same truth.

    Keyed by ``sim`` for the scenario's own method (uimm-est) and by ``(sim, "uimm")``
    for the fixed-size UIMM.
    """
    out = {}
    for sim in (1, 2):
        for key, changes in ((sim, {}), ((sim, "uimm"), {"filter__method": "uimm"})):
            if changes:  # the tuned file's [filter.est] is uimm-est's only
                d = short_dict(sim, **changes)
                d["filter"].pop("est")
                sc = parse_scenario(d)
            else:
                sc = short_scenario(sim)
            r64 = run_scenario(sc, chunk=CHUNK)
            r32 = run_scenario_float32(sc, chunk=CHUNK)
            out[key] = (sc, r64, r32)
    return out


@pytest.mark.parametrize("method", ["uimm-est", "uimm"])
@pytest.mark.parametrize("sim", [1, 2])
def test_float32_agrees_with_float64_on_the_tuned_scenarios(pair, sim, method):
    sc, r64, r32 = pair[sim if method == "uimm-est" else (sim, method)]
    assert sc.filter.method == method
    assert r32.summary["dtype"] == "float32" and r64.summary["dtype"] == "float64"
    assert r32.outputs["mode_probs"].dtype == np.float32
    np.testing.assert_array_equal(r32.truth["y"], r64.truth["y"])  # same float64 truth
    assert all_finite(r32.outputs)
    agree = float32_agreement(
        r64.outputs, r32.outputs, r64.summary["declarations"], r32.summary["declarations"]
    )
    assert agree["same_faults"], (r64.summary["declarations"], r32.summary["declarations"])
    assert [d["fault"] for d in r32.summary["declarations"]] == [e.fault for e in sc.events]
    assert agree["declaration_time_diff_s"] <= DECLARATION_TOLERANCE_S
    assert agree["mean_abs_mode_prob_diff"] < MODE_PROB_TOLERANCE[method]
    assert agree["recognised_disagreement"] < 1e-3
    for d64, d32 in zip(r64.summary["declarations"], r32.summary["declarations"], strict=True):
        if "magnitude" in d64:  # uimm-est: the estimated sizes agree
            assert d32["magnitude"] == pytest.approx(d64["magnitude"], rel=MAGNITUDE_TOLERANCE)
    assert r32.summary["health"] == r64.summary["health"]
    # The float32 estimate stays within the measurement noise of float64's (typically
    # 1 % of it; the largest gaps are at the fault onsets).
    sigma = np.sqrt(np.diag(sc.measurement_noise))
    dx = np.abs(r32.outputs["mean"] - r64.outputs["mean"])
    assert np.all(dx.max(axis=0) < 2.0 * sigma), dx.max(axis=0) / sigma
    assert np.all(np.quantile(dx, 0.99, axis=0) < 0.05 * sigma)


def test_cli_float32_flag(tmp_path, pair, monkeypatch, capsys):
    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)  # main() replaces it
    _, _, r32 = pair[1]
    path = write_short(tmp_path / "s.toml", 1)
    out = tmp_path / "out"
    assert (
        cli.main(["run", str(path), "--float32", "--no-plots", "--quiet", "--out", str(out)]) == 0
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dtype"] == "float32" and summary["scaling"] == r32.summary["scaling"]
    for key in ("declarations", "detection_delay_s", "mode_accuracy", "health"):
        assert summary[key] == r32.summary[key], key
    assert "error" not in capsys.readouterr().err


def micro_scenario():
    """The short tuned sim 1 in "micro units": input x 2^-20, every variance x 2^-40.

    The plant is linear and starts at rest, so every signal scales by 2^-20: in float64
    the diagnosis is the same.  Unscaled float32 cannot hold variances of 1e-24 above its
    Cholesky floor; the scaled mode does not care about units.
    """
    c = 2.0**-20
    d = short_dict(1)
    d["input"]["amplitude"] *= c
    d["noise"]["process"] = [v * c * c for v in d["noise"]["process"]]
    d["noise"]["measurement"] = [v * c * c for v in d["noise"]["measurement"]]
    d["filter"]["initial_cov"] = np.asarray(d["filter"]["initial_cov"]) * c * c
    return parse_scenario(d, source="micro")


def _assert_same_declarations(a: list[dict], b: list[dict]) -> None:
    """Equal declarations; uimm-est's estimated sizes equal up to rounding (1e-9)."""
    assert len(a) == len(b), (a, b)
    for da, db in zip(a, b, strict=True):
        sizes = ("magnitude", "magnitude_ci")
        assert {k: v for k, v in da.items() if k not in sizes} == {
            k: v for k, v in db.items() if k not in sizes
        }
        for key in sizes:
            if key in da:
                np.testing.assert_allclose(da[key], db[key], rtol=1e-9)


def test_scaling_makes_float32_independent_of_units(pair):
    sc = micro_scenario()
    r64 = run_scenario(sc, chunk=CHUNK)
    _, base64, _ = pair[1]
    # units do not matter (the estimated sizes up to rounding)
    _assert_same_declarations(r64.summary["declarations"], base64.summary["declarations"])
    r32 = run_scenario_float32(sc, chunk=CHUNK)
    d64, d32 = r64.summary["declarations"], r32.summary["declarations"]
    scaled = float32_agreement(r64.outputs, r32.outputs, d64, d32)
    assert scaled["same_faults"] and scaled["declaration_time_diff_s"] <= DECLARATION_TOLERANCE_S
    assert scaled["mean_abs_mode_prob_diff"] < 1e-3
    assert r32.summary["health"]["cov_repaired_steps"] == 0
    # Without scaling, float32 repairs the innovation covariance at nearly every step.
    with jax.enable_x64(False):
        setup = setup_scenario(sc, dtype=jnp.float32)
        y, u = (r64.truth[k].astype(np.float32) for k in ("y", "u"))
        _, raw = filter_measurements(setup, y, u, chunk=CHUNK)
    s_raw = summarize(setup, r64.truth["truth"], raw, runtime_s=1.0)
    assert np.mean(raw["health"] & HEALTH_COV_REPAIRED > 0) > 0.9
    unscaled = float32_agreement(r64.outputs, raw, d64, s_raw["declarations"])
    assert unscaled["mean_abs_mode_prob_diff"] > 10 * scaled["mean_abs_mode_prob_diff"]
