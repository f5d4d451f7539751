"""Exports and the standard FDI rates: timeseries.npz/csv of a run, TDR/FAR/FIA definitions.

The rates are checked against a naive per-sample loop written here from the definitions of
docs/montecarlo.md; the exports against the run's own outputs.  runs.csv is tested with the
sweep fixture in test_montecarlo.py.
"""

from __future__ import annotations

import csv
import json

import jax.numpy as jnp
import numpy as np
import pytest

from _robustness_helpers import write_short
from uimm_jax import cli
from uimm_jax.engine import metrics
from uimm_jax.studies.exports import TIMESERIES_KEYS, decimation_steps


def _naive_rates(code, declared, prob):
    faulty = flagged_faulty = flagged_free = 0
    prob_sum = 0.0
    for c, d, p in zip(code, declared, prob, strict=True):
        if c:
            faulty += 1
            if d:
                flagged_faulty += 1
                prob_sum += p
        elif d:
            flagged_free += 1
    free = len(code) - faulty
    return {
        "tdr": flagged_faulty / faulty if faulty else None,
        "far": flagged_free / free if free else None,
        "fia": prob_sum / flagged_faulty if flagged_faulty else None,
    }


@pytest.mark.parametrize("seed", [0, 42, 99])
def test_fdi_rates_match_a_per_sample_loop(seed):
    rng = np.random.default_rng(seed)
    N = 500
    code = rng.integers(0, 4, N) * (rng.random(N) < 0.6)
    declared = rng.integers(0, 8, N) * (rng.random(N) < 0.5)
    prob = rng.random(N)
    terms = metrics.fdi_terms(jnp.asarray(code), jnp.asarray(declared), jnp.asarray(prob))
    counts = metrics.FDICounts(*(np.sum(np.asarray(t)) for t in terms))
    got = metrics.fdi_rates(counts, N)
    want = _naive_rates(code, declared, prob)
    assert got["tdr"] == want["tdr"] and got["far"] == want["far"]
    assert got["fia"] == pytest.approx(want["fia"], rel=1e-12)


def test_fdi_rates_without_a_denominator_are_none():
    zeros = np.zeros(10, int)
    terms = metrics.fdi_terms(jnp.asarray(zeros), jnp.asarray(zeros), jnp.zeros(10))
    counts = metrics.FDICounts(*(np.sum(np.asarray(t)) for t in terms))
    assert metrics.fdi_rates(counts, 10) == {"tdr": None, "far": 0.0, "fia": None}


def test_true_set_probability_sums_the_models_of_the_true_set():
    rng = np.random.default_rng(3)
    probs = rng.random((4, 6))
    probs /= probs.sum(0)
    model_codes = np.array([[1, 1, 0, 2, 2, 5]] * 4)
    model_codes[1:, :] = [[3], [5], [9]]
    truth = np.array([1, 3, 7, 2, 9, 5])
    got = np.asarray(metrics.true_set_probability(probs, model_codes, truth))
    want = [sum(probs[m, r] for m in range(4) if model_codes[m, r] == truth[r]) for r in range(6)]
    np.testing.assert_allclose(got, want, rtol=1e-15)
    # (M,) codes broadcast over the runs (the combinatorial bank).
    got = np.asarray(metrics.true_set_probability(probs, np.arange(4), truth))
    want = [probs[truth[r], r] if truth[r] < 4 else 0.0 for r in range(6)]
    np.testing.assert_allclose(got, want, rtol=1e-15)


def test_sample_time_is_rounded_to_the_sample():
    assert metrics.sample_time(600207, 1e-4) == 60.0207  # 600207 * 1e-4 = 60.020700000000005
    assert metrics.sample_time(391, 1e-4) == 0.0391
    for k in (1, 7, 12345, 999_999):
        assert metrics.sample_time(k, 1e-4) == pytest.approx(k * 1e-4, rel=1e-12)


def test_decimation_keeps_every_change():
    declared = np.array([0, 0, 0, 0, 1, 1, 1, 1, 1, 3, 3])
    recognised = np.array([0, 0, 1, 0, 1, 1, 1, 3, 3, 3, 3])
    rows = decimation_steps(declared, recognised, 5)
    assert list(rows) == [0, 2, 3, 4, 5, 7, 9, 10]


def _cli_out(tmp_path_factory, name: str, sim: int, *flags: str):
    """``uimm-jax run`` of the short tuned scenario ``sim`` with ``flags``: its out folder."""
    tmp = tmp_path_factory.mktemp(name)
    path = write_short(tmp / "short.toml", sim)
    out = tmp / "out"
    assert cli.main(["run", str(path), "--quiet", "--no-plots", *flags, "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def run_out(tmp_path_factory):
    return _cli_out(tmp_path_factory, "exports", 1, "--csv", "50")


def test_run_writes_timeseries_npz(run_out):
    summary = json.loads((run_out / "summary.json").read_text())
    with np.load(run_out / "timeseries.npz") as z:
        a = {k: z[k] for k in z.files}
    N, M, n = summary["num_steps"], summary["num_models"], 3
    assert set(TIMESERIES_KEYS) <= set(a)
    assert a["time"].shape == (N,) and a["mode_probs"].shape == (N, M)
    assert a["recognised"].shape == a["declared"].shape == a["health"].shape == (N,)
    assert a["mean"].shape == (N, n)
    np.testing.assert_allclose(a["time"], (np.arange(N) + 1) * summary["dt"], rtol=1e-12)
    np.testing.assert_allclose(a["mode_probs"].sum(1), 1.0, atol=1e-12)
    assert list(a["faults"]) == summary["faults"]
    # The summary's declarations and rates follow from the exported arrays.
    for d in summary["declarations"]:
        j = summary["faults"].index(d["fault"])
        k = int(np.argmax((a["declared"] >> j) & 1))
        assert a["time"][k] == pytest.approx(d["time"], abs=1e-12)
    flagged = a["declared"] != 0
    faulty = a["truth"] != 0
    assert summary["tdr"] == np.sum(flagged & faulty) / np.sum(faulty)
    assert summary["far"] == np.sum(flagged & ~faulty) / np.sum(~faulty)
    assert 0.9 < summary["fia"] <= 1.0  # the tuned scenario isolates both faults


def _naive_run_rates(z) -> dict:
    """TDR, FAR, FIA of one run from its timeseries.npz, written from docs/montecarlo.md.

    Each model's fault set is read from its label: for UIMM ("D (no new fault)", "D + f")
    D is the declared set before the sample; for the size-estimating UIMM ("D (no change)",
    "D +/- f") it is D with f toggled; for IMM ("fault-free", "f + g") it is fixed.
    """
    bit = {name: 1 << j for j, name in enumerate(z["faults"])}
    declared, truth, mu = z["declared"], z["truth"], z["mode_probs"]
    N, M = mu.shape
    d_before = np.concatenate([[0], declared[:-1]])
    sets = np.zeros((N, M), np.int64)
    for m, label in enumerate(z["model_labels"]):
        names = [w.strip(" /-") for w in str(label).split("+")]
        uimm = names[0].startswith("D")
        code = sum(bit[w] for w in names if w in bit)
        toggle = "+/-" in str(label)
        sets[:, m] = (d_before ^ code) if toggle else (d_before | code) if uimm else code
    faulty, flagged = truth != 0, declared != 0
    detected = faulty & flagged
    true_prob = np.sum(np.where(sets == truth[:, None], mu, 0.0), axis=1)
    return {
        "tdr": detected.sum() / faulty.sum(),
        "far": (flagged & ~faulty).sum() / (~faulty).sum(),
        "fia": true_prob[detected].mean(),
    }


@pytest.fixture(scope="module")
def imm_run_out(tmp_path_factory):
    # a warning line: initial_mode_probs adapted for "imm"
    return _cli_out(tmp_path_factory, "exports_imm", 2, "--method", "imm")


@pytest.fixture(scope="module")
def uimm_run_out(tmp_path_factory):
    return _cli_out(tmp_path_factory, "exports_uimm", 1, "--method", "uimm")


@pytest.mark.parametrize("fixture", ["run_out", "uimm_run_out", "imm_run_out"])
def test_run_rates_match_a_naive_reference_from_the_exports(fixture, request):
    """summary.json's TDR/FAR/FIA = a per-sample loop over timeseries.npz (all three methods)."""
    out = request.getfixturevalue(fixture)
    summary = json.loads((out / "summary.json").read_text())
    with np.load(out / "timeseries.npz") as z:
        want = _naive_run_rates({k: z[k] for k in z.files})
    assert summary["tdr"] == want["tdr"] and summary["far"] == want["far"]
    assert summary["fia"] == pytest.approx(want["fia"], rel=1e-12)
    assert 0.0 < want["tdr"] < 1.0 and 0.5 < want["fia"] <= 1.0  # not a trivial run


def test_run_writes_decimated_csv(run_out):
    with np.load(run_out / "timeseries.npz") as z:
        declared, recognised = z["declared"], z["recognised"]
        mode_probs, label0 = z["mode_probs"], str(z["model_labels"][0])
    rows = list(csv.DictReader((run_out / "timeseries.csv").open()))
    steps = [int(r["step"]) for r in rows]
    assert steps == list(decimation_steps(declared, recognised, 50))
    assert len(rows) < len(declared) / 10
    for r in rows[::37]:
        k = int(r["step"])
        assert int(r["declared"]) == declared[k]
        assert float(r[f"mode_prob:{label0}"]) == pytest.approx(mode_probs[k, 0], 1e-8)
    assert rows[-1]["declared_set"] == "valve_wear+leakage"


def test_run_csv_flag_is_checked(tmp_path, capsys):
    path = write_short(tmp_path / "s.toml", 1)
    assert cli.main(["run", str(path), "--csv", "-3", "--out", str(tmp_path / "o")]) == 2
    assert "--csv" in capsys.readouterr().err


@pytest.mark.parametrize("method", ["uimm", "imm"])
def test_diagnoser_true_set_log_prob_is_the_generic_definition(method):
    """The fast per-step FIA term equals the sum over the models of the true set."""
    import warnings

    import jax

    from uimm_jax.engine.bank import set_codes
    from uimm_jax.scenario.parse import load_scenario
    from uimm_jax.studies.run import setup_scenario

    sc = load_scenario("scenarios/paper_sim1_tuned.toml")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # initial_mode_probs adapted for "imm"
        diag = setup_scenario(sc, method).diagnoser
    F, M, B = diag.num_faults, diag.num_models, 64
    rng = np.random.default_rng(5)
    declared = jnp.asarray(rng.random((F, B)) < 0.4)
    code = jnp.asarray(rng.integers(0, 2**F, B), jnp.int32)
    code = code.at[:8].set(set_codes(declared)[:8])  # the true set is D itself
    log_p = jax.nn.log_softmax(jnp.asarray(rng.normal(size=(M, B))), axis=0)
    if method == "uimm":  # declared hypotheses are masked out of the bank
        active = jnp.concatenate([jnp.ones((1, B), bool), ~declared], 0)
        log_p = jnp.where(active, log_p, -jnp.inf)
    got = np.exp(np.asarray(diag.true_set_log_prob(log_p, declared, code)))
    model_codes = set_codes(diag.model_sets(declared))
    want = np.asarray(metrics.true_set_probability(jnp.exp(log_p), model_codes, code))
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=0)
    assert (want > 0).sum() > B // 4
    if method == "uimm":  # some true sets are held by no model of the bank
        assert (want == 0).sum() > 0


def test_run_exports_the_leading_models_nis_and_summarises_it(run_out):
    """``nis`` in timeseries.npz/csv is the most probable model's ``e' S^-1 e`` per channel
    (``chi^2_3 / 3`` at the filter's own noise: its median is 0.79, its mean 1), and
    summary.json's ``innovation_check`` is its mean, with a consistent verdict."""
    summary = json.loads((run_out / "summary.json").read_text())
    with np.load(run_out / "timeseries.npz") as z:
        nis = z["nis"]
    assert nis.shape == (summary["num_steps"],) and np.all(nis >= 0)
    ic = summary["innovation_check"]
    assert ic["mean_nis_per_channel"] == pytest.approx(float(np.mean(nis)), rel=1e-12)
    assert 0.9 < ic["mean_nis_per_channel"] < 1.1 and ic["verdict"] == "consistent"
    assert ic["samples"] == nis.size and ic["band_99"][0] < 1.0 < ic["band_99"][1]
    assert 0.7 < np.median(nis) < 0.9  # chi^2_3 / 3: 0.789
    rows = list(csv.DictReader((run_out / "timeseries.csv").open()))
    for r in rows[::41]:
        assert float(r["nis"]) == pytest.approx(nis[int(r["step"])], rel=1e-9)


def test_run_exports_each_outputs_nis_and_summarises_it_by_output(run_out):
    """``nis_channels`` in timeseries.npz (``nis:<output>`` in the csv) is the same model's
    ``e_i^2 / S_ii`` per measured output (``chi^2_1``: median 0.455, mean 1), and
    summary.json's ``innovation_check.by_channel`` holds each output's mean and verdict."""
    summary = json.loads((run_out / "summary.json").read_text())
    with np.load(run_out / "timeseries.npz") as z:
        ch, outputs = z["nis_channels"], [str(o) for o in z["outputs"]]
    N = summary["num_steps"]
    assert ch.shape == (N, len(outputs)) and np.all(ch >= 0)
    by = summary["innovation_check"]["by_channel"]
    assert list(by) == outputs
    for i, name in enumerate(outputs):
        assert by[name]["mean_nis"] == pytest.approx(float(np.mean(ch[:, i])), rel=1e-12)
        assert by[name]["verdict"] == "consistent" and by[name]["samples"] == N
        assert 0.35 < np.median(ch[:, i]) < 0.55  # chi^2_1: 0.455
    rows = list(csv.DictReader((run_out / "timeseries.csv").open()))
    for r in rows[::41]:
        got = [float(r[f"nis:{o}"]) for o in outputs]
        np.testing.assert_allclose(got, ch[int(r["step"])], rtol=1e-9)


@pytest.mark.parametrize(("scale", "verdict"), [(2.0, "noise too small"), (0.5, "noise too large")])
def test_innovation_check_flags_measurement_noise_the_filter_misjudges(scale, verdict):
    """The truth's measurement noise sd x2 (x0.5), the filter's as given: the NIS scales by
    4 (0.25) on the two channels whose innovation the noise dominates and stays about 1 on
    the third (its innovation is the state's), so the mean per channel is about (2 x 4 +
    1) / 3 = 3 ((2 x 0.25 + 1) / 3 = 0.5), and the verdict says so."""
    from _robustness_helpers import short_dict
    from uimm_jax.scenario.parse import parse_scenario
    from uimm_jax.studies.run import execute_run, filter_measurements, setup_scenario

    d = short_dict(1, duration=0.3, events=(0.1, 0.2))
    sc = parse_scenario(d)
    d["noise"]["measurement"] = [v * scale**2 for v in d["noise"]["measurement"]]
    truth = setup_scenario(parse_scenario(d))
    r = execute_run(setup_scenario(sc), filter_measurements, truth_setup=truth, seed=0)
    ic = r.summary["innovation_check"]
    assert ic["verdict"] == verdict
    assert ic["mean_nis_per_channel"] == pytest.approx((2 * scale**2 + 1) / 3, rel=0.1)


@pytest.mark.parametrize("channel", [0, 1, 2])
def test_innovation_check_by_output_names_the_one_whose_noise_is_off(channel):
    """The truth's measurement noise sd x2 on one output only: that output's own mean
    ``e_i^2 / S_ii`` leaves the band and the others stay consistent (measured on 5 s of
    sim 1: 2.7, 2.7 and 3.6 on the output scaled, 0.99-1.04 elsewhere)."""
    from _robustness_helpers import short_dict
    from uimm_jax.scenario.parse import parse_scenario
    from uimm_jax.studies.run import execute_run, filter_measurements, setup_scenario

    d = short_dict(1, duration=0.3, events=(0.1, 0.2))
    sc = parse_scenario(d)
    d["noise"]["measurement"][channel] *= 4.0
    truth = setup_scenario(parse_scenario(d))
    r = execute_run(setup_scenario(sc), filter_measurements, truth_setup=truth, seed=0)
    by = r.summary["innovation_check"]["by_channel"]
    names = list(sc.plant.output_names)
    assert list(by) == names
    off = [k for k, v in by.items() if v["verdict"] != "consistent"]
    assert off == [names[channel]] and by[names[channel]]["verdict"] == "noise too small"


def test_unexplained_spells_find_a_stretch_of_large_innovations_and_nothing_else():
    """``unexplained_spells``: on chi-square data of the filter's own noise, no spell; with
    a stretch of 4x larger innovations, one spell covering it to within a window; a
    stretch shorter than 3 windows or with nothing observed makes none."""
    rng = np.random.default_rng(2)
    dt, N, m = 1e-3, 20_000, 3
    ch = rng.chisquare(1, (N, m))  # uncorrelated outputs: e' S^-1 e is their sum
    nis = ch.mean(axis=1)
    assert metrics.unexplained_spells(nis, ch, dt) == []
    bad = nis.copy()
    bad[5000:9000] *= 4.0  # 4 s
    bad[12000:12150] *= 4.0  # 0.15 s: 2 windows of 0.1 s, under 3
    spells = metrics.unexplained_spells(bad, ch, dt)
    assert len(spells) == 1
    assert 5.0 <= spells[0]["start"] <= 5.1 and 8.9 <= spells[0]["end"] <= 9.0
    assert 3.5 < spells[0]["peak_nis"] < 5.0
    gap = bad.copy()
    gap[5000:9000] = np.nan  # nothing observed there: nothing to flag
    assert metrics.unexplained_spells(gap, np.where(np.isnan(gap)[:, None], np.nan, ch), dt) == []
    assert metrics.unexplained_spells(bad, ch, dt, windows=2)[1]["start"] == pytest.approx(12.001)


@pytest.mark.parametrize(("method", "flagged"), [("uimm", True), ("uimm-est", False)])
def test_unexplained_flags_the_fixed_uimm_on_a_fault_off_its_library_size(method, flagged):
    """Valve wear at 3x its library size from 0.4 s: the fixed-size UIMM cannot explain
    the data from there (docs/montecarlo.md: NIS 1e2-1e5), uimm-est can."""
    from _robustness_helpers import short_dict
    from uimm_jax.scenario.parse import parse_scenario
    from uimm_jax.studies.run import run_scenario

    d = short_dict(1, duration=1.2, events=(0.4, 0.5))
    d["events"] = [{"time": 0.4, "fault": "valve_wear", "magnitude": 3.0}]
    d["filter"]["method"] = method
    if method == "uimm":
        d["filter"].pop("est", None)
    spells = run_scenario(parse_scenario(d)).summary["innovation_check"]["unexplained"]
    if flagged:
        assert len(spells) == 1 and 0.4 <= spells[0]["start"] <= 0.5
        assert spells[0]["end"] == pytest.approx(1.2) and spells[0]["peak_nis"] > 100
    else:
        assert spells == []


def test_innovation_check_of_chi_square_samples_and_of_nothing_observed():
    rng = np.random.default_rng(0)
    m = 3
    ok = metrics.innovation_check(rng.chisquare(m, 20_000) / m)
    assert ok["verdict"] == "consistent"
    assert ok["band_99"][0] <= ok["mean_nis_per_channel"] <= ok["band_99"][1]
    big = metrics.innovation_check(4.0 * rng.chisquare(m, 1000) / m)
    assert big["verdict"] == "noise too small"
    none = metrics.innovation_check(np.full(5, np.nan))
    assert none["verdict"] is None and none["samples"] == 0
    # By channel: chi^2_1 samples, the second channel's x4 and with gaps (NaN: missing).
    ch = rng.chisquare(1, (4000, 3))
    ch[:, 1] *= 4.0
    ch[::4, 2] = np.nan
    by = metrics.innovation_check(np.nanmean(ch, axis=1), ch, ["a", "b", "c"])["by_channel"]
    assert [by[k]["verdict"] for k in "abc"] == ["consistent", "noise too small", "consistent"]
    assert by["c"]["samples"] == 3000 and by["c"]["mean_nis"] == pytest.approx(
        float(np.nanmean(ch[:, 2])), rel=1e-12
    )
    unnamed = metrics.innovation_check(np.full(2, np.nan), np.full((2, 2), np.nan))
    assert unnamed["by_channel"]["1"] == {
        "mean_nis": None,
        "band_99": None,
        "samples": 0,
        "verdict": None,
    }
