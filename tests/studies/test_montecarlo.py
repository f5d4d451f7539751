"""Monte Carlo sweeps: spec validation, metrics vs a loop of single runs, sharding, CLI.

The sweep's fused kernel (truth + diagnoser + metrics in one scan over a batch of runs) is
checked against a Python loop of single runs built from the engine's single-run pieces
(``truth_step`` in a scan, ``run.filter_measurements``, ``run.summarize``) with the
same per-run keys; the onset draws are recomputed here from the documented key recipe.
The sharded run (4 forced CPU devices) runs in a subprocess started when the module's
fixture is first used, in parallel with the in-process tests.
"""

import functools
import json
import os
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from _reference import philox4x32
from uimm_jax.engine import metrics
from uimm_jax.engine.noise import box_muller
from uimm_jax.engine.truth import truth_step
from uimm_jax.errors import ScenarioError
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.sweep import sweep_spec
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.studies import run
from uimm_jax.studies import sweep as mc
from uimm_jax.studies.sweep_outputs import SweepResult

ROOT = Path(__file__).resolve().parents[2]
SEED = 7
RUNS = 2
BATCH = 32  # 10 cells x 2 runs: one batch, padded to 8 runs per device on 4 devices

SWEEP = {
    "runs": RUNS,
    "seed": SEED,
    "methods": ["uimm"],
    "magnitudes": [0.6, 1.0],
    "noise_scales": [1.0, 2.0],
    "fault_free": True,
    "batch": BATCH,
    "chunk": 100_000,
    "cases": [
        {
            "name": "sim1",
            "events": [
                {"fault": "valve_wear", "time": 0.05},
                {"fault": "leakage", "time": [0.09, 0.12]},
            ],
        },
        {
            "name": "sim2",
            "events": [
                {"fault": "valve_wear", "time": [0.03, 0.07]},
                {"fault": "air_in_oil", "time": 0.1, "magnitude": 0.8},
            ],
        },
    ],
}


def small_scenario(sweep=None):
    """paper_sim1_tuned shortened to 2000 samples, with a [sweep] table."""
    d = scenario_to_dict(load_scenario(ROOT / "scenarios" / "paper_sim1_tuned.toml"))
    d["duration"] = 0.2
    d["events"] = [
        {"time": 0.05, "fault": "valve_wear"},
        {"time": 0.1, "fault": "leakage"},
    ]
    d["sweep"] = SWEEP if sweep is None else sweep
    return parse_scenario(d, source="small")


_SUBPROCESS = textwrap.dedent(
    """
    import sys
    sys.path[:0] = [{tests!r}, {root!r}]
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    from test_montecarlo import small_scenario
    from uimm_jax.studies import sweep as mc

    assert len(jax.devices()) == 4, jax.devices()
    res = mc.run_sweep(small_scenario())
    assert res.devices == 4
    np.savez({out!r}, decl_step=res.decl_step, onset_step=res.onset_step,
             correct=res.correct_samples, sq_err=res.sq_err, health=res.health)
    """
)


@pytest.fixture(scope="module")
def sharded_proc(tmp_path_factory):
    """Start the 4-device sweep in a subprocess (collected by the sharding test)."""
    out = tmp_path_factory.mktemp("sharded") / "sharded.npz"
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
    ).strip()
    env["JAX_PLATFORMS"] = "cpu"
    here = Path(__file__).parent
    code = _SUBPROCESS.format(tests=str(here), root=str(here.parent), out=str(out))
    proc = subprocess.Popen(
        [sys.executable, "-c", code],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    yield proc, out
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


@pytest.fixture(scope="module")
def sweep(sharded_proc):
    del sharded_proc  # started first, so that it runs while this one compiles
    return mc.run_sweep(small_scenario())


# --------------------------------------------------------------------------------------
# Specification
# --------------------------------------------------------------------------------------


def test_spec_defaults_from_scenario():
    sc = load_scenario(ROOT / "scenarios" / "paper_sim2_tuned.toml")
    spec = sweep_spec(sc)
    assert spec.runs == 100 and spec.seed == sc.seed
    assert spec.methods == ("uimm-est",) and spec.magnitudes == (1.0,)  # the file's method
    assert spec.fault_free
    assert len(spec.cases) == 1
    assert [(e.fault, e.time) for e in spec.cases[0].events] == [
        ("valve_wear", (30.0, 30.0)),
        ("air_in_oil", (60.0, 60.0)),
    ]
    spec = sweep_spec(sc, runs=3, methods=["imm", "uimm"], magnitudes=[0.5, 1.0])
    assert (spec.runs, spec.methods, spec.magnitudes) == (3, ("imm", "uimm"), (0.5, 1.0))
    cells = mc._cells(spec)
    assert len(cells) == 2 * (1 + 2)
    assert [c.index for c in cells] == list(range(len(cells)))


@pytest.mark.parametrize(
    ("patch", "field", "words"),
    [
        ({"runs": 0}, "[sweep].runs", ">= 1"),
        ({"runs": 2.5}, "[sweep].runs", "integer"),
        ({"rusn": 3}, "[sweep].rusn", "unknown key"),
        ({"methods": ["ukf"]}, "[sweep].methods[0]", "must be one of uimm, imm, uimm-est"),
        ({"methods": ["uimm", "uimm"]}, "[sweep].methods", "repeated"),
        ({"magnitudes": [1.0, -0.5]}, "[sweep].magnitudes[1]", "> 0"),
        ({"noise_scales": []}, "[sweep].noise_scales", "non-empty"),
        ({"fault_free": "yes"}, "[sweep].fault_free", "true or false"),
        ({"seed": -1}, "[sweep].seed", "in [0, 4294967295], got -1"),
        ({"seed": 2**32}, "[sweep].seed", "in [0, 4294967295], got 4294967296"),
        (
            {"cases": [{"name": "x", "events": [{"fault": "leakage", "time": 0.19996}]}]},
            "[sweep].cases[0].events[0].time",
            "samples are 0..1999: the fault would never occur",
        ),
        ({"batch": 0}, "[sweep].batch", ">= 1"),
        ({"cases": {"a": 1}}, "[sweep].cases", "array of tables"),
        (
            {"cases": [{"name": "x", "events": [{"fault": "wear", "time": 0.1}]}]},
            "[sweep].cases[0].events[0].fault",
            "unknown fault 'wear'",
        ),
        (
            {"cases": [{"name": "x", "events": [{"fault": "leakage", "time": 0.5}]}]},
            "[sweep].cases[0].events[0].time",
            "outside the run",
        ),
        (
            {"cases": [{"name": "x", "events": [{"fault": "leakage", "time": [0.1, 0.05]}]}]},
            "[sweep].cases[0].events[0].time",
            "reversed",
        ),
        (
            {"cases": [{"name": "x", "events": [{"fault": "leakage"}]}]},
            "[sweep].cases[0].events[0].time",
            "missing",
        ),
        (
            {
                "cases": [
                    {
                        "name": "x",
                        "events": [
                            {"fault": "leakage", "time": 0.1},
                            {"fault": "leakage", "time": 0.15},
                        ],
                    }
                ]
            },
            "[sweep].cases[0].events",
            "occurs twice",
        ),
        (
            {"cases": [{"name": "fault-free", "events": [{"fault": "leakage", "time": 0.1}]}]},
            "[sweep].cases[0].name",
            "reserved",
        ),
        ({"cases": [{"name": "x", "events": []}]}, "[sweep].cases[0].events", "non-empty"),
        (
            {"cases": [{"name": "x", "events": [{"fault": "leakage", "time": 0.1, "mag": 2}]}]},
            "[sweep].cases[0].events[0].mag",
            "unknown key",
        ),
    ],
)
def test_spec_errors_name_the_field(patch, field, words):
    sc = small_scenario({**SWEEP, **patch})
    with pytest.raises(ScenarioError) as err:
        sweep_spec(sc)
    assert err.value.field == field
    assert words in str(err.value)
    assert str(err.value).startswith("small: " + field)


def test_nothing_to_run_is_an_error():
    sc = small_scenario({"fault_free": False, "cases": []})
    with pytest.raises(ScenarioError, match="nothing to run"):
        sweep_spec(sc)


def test_argument_overrides_are_validated():
    sc = small_scenario()
    with pytest.raises(ScenarioError) as err:
        sweep_spec(sc, runs=0)
    assert err.value.field == "runs"


# --------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("k", "n"), [(0, 10), (3, 10), (10, 10), (57, 64), (1, 1)])
def test_wilson_interval_matches_scipy(k, n):
    stats = pytest.importorskip("scipy.stats")
    ref = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    lo, hi = metrics.wilson_interval(k, n)
    np.testing.assert_allclose([lo, hi], [ref.low, ref.high], rtol=1e-12, atol=1e-15)
    assert metrics.wilson_interval(0, 0) is None


def test_confusion_definition():
    N = 100
    # faults: 0, 1, 2 ; rows: fault-free, f0, f1, f2 ; columns: f0, f1, f2, none
    onset = np.array(
        [
            [10, 50, -1],  # f0 then f1
            [10, 50, -1],
            [10, 50, -1],
            [-1, -1, -1],  # fault-free run
            [20, 20, -1],  # simultaneous onsets
        ]
    )
    decl = np.array(
        [
            [12, 55, -1],  # both isolated in their windows
            [60, 70, -1],  # f0 late (outside its window): f0 row 'none'; f1 row: f1
            [5, -1, 52],  # false f0 before onset; f0 row none; f1 row -> f2
            [-1, 30, 30],  # fault-free: first declarations tie -> lowest index (f1)
            [25, 25, -1],  # tie within the window: each event gets its own fault
        ]
    )
    got = metrics.confusion(onset, decl, N)
    want = np.zeros((4, 4), int)
    want[0, 3] += 1  # run 0 fault-free period
    want[1, 0] += 1
    want[2, 1] += 1
    want[0, 3] += 1  # run 1
    want[1, 3] += 1
    want[2, 1] += 1
    want[0, 0] += 1  # run 2: false f0 in the fault-free period
    want[1, 3] += 1  # f0 already declared before its onset: nothing new in [10, 50)
    want[2, 2] += 1
    want[0, 1] += 1  # run 3
    want[0, 3] += 1  # run 4
    want[1, 0] += 1
    want[2, 1] += 1
    np.testing.assert_array_equal(got, want)
    # Per run (what tune.evaluate's "every fault declared and isolated" uses): only runs
    # 0 and 4 isolate every event; the fault-free run 3 has no event to isolate.
    fake = types.SimpleNamespace(onset_step=onset[None], decl_step=decl[None], num_steps=N)
    np.testing.assert_array_equal(SweepResult.isolated(fake), [[True, False, False, True, True]])


# --------------------------------------------------------------------------------------
# The fused kernel against a loop of single runs
# --------------------------------------------------------------------------------------


def _documented_normals(key, num_steps):
    """The truth's normals of one run, ``(N, 6)``: step k's pair i is the Box-Muller
    transform of the NumPy Philox words of counter ``(k, i, 0, 0)`` (engine/noise.py)."""
    ks, i = np.meshgrid(np.arange(num_steps), np.arange(3), indexing="ij")
    w = philox4x32((key[0], key[1]), (ks, i, 0, 0))  # each (N, 3)
    a, b = ((hi.astype(np.uint64) << np.uint64(32)) | lo for hi, lo in (w[:2], w[2:]))
    zc, zs = box_muller(jnp.asarray(a), jnp.asarray(b), jnp.float64)
    return jnp.stack([zc, zs], axis=-1).reshape(num_steps, 6)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _simulate_one(dyn, dt, num_steps, plan, signal, zs):
    from uimm_jax.engine.truth import input_value

    def body(x, kz):
        k, z = kz
        t = k.astype(x.dtype) * dt
        u = jnp.full((1,), input_value(signal, t), x.dtype)
        xn, y, code = truth_step(dyn, plan, x, k, u, z)
        return xn, (u, xn, y, code)

    ks = jnp.arange(num_steps, dtype=jnp.int32)
    _, out = jax.lax.scan(body, jnp.zeros(3), (ks, zs))
    return out


def _onset_draw(seed, runs, r, e, lo, hi, dt):
    """The documented recipe, recomputed independently of engine.truth.run_keys."""
    if hi == lo:
        return int(round(lo / dt))
    key = jax.random.split(jax.random.PRNGKey(seed), runs)[r]
    draw_key = jax.random.split(key)[1]
    u = float(jax.random.uniform(jax.random.fold_in(draw_key, e), (), jnp.float64))
    return int(round((lo + (hi - lo) * u) / dt))


def _reference(sc, cell, r):
    """One run with the engine's single-run pieces: summary, truth states and estimates."""
    d = scenario_to_dict(sc)
    d.pop("sweep")
    events = []
    if cell.case != "fault-free":
        case = next(c for c in SWEEP["cases"] if c["name"] == cell.case)
        for e, ev in enumerate(case["events"]):
            t = ev["time"]
            lo, hi = (t, t) if not isinstance(t, list) else t
            step = _onset_draw(SEED, RUNS, r, e, lo, hi, sc.dt)
            events.append(
                {"fault": ev["fault"], "time": step * sc.dt, "magnitude": ev.get("magnitude", 1.0)}
            )
    d["events"] = events
    one = parse_scenario(d)
    setup = run.setup_scenario(one, cell.method, magnitude_scale=cell.magnitude or 1.0)
    plan = setup.plan._replace(
        Gq=setup.plan.Gq * cell.noise_scale, Gr=setup.plan.Gr * cell.noise_scale
    )
    key = jax.random.split(jax.random.split(jax.random.PRNGKey(SEED), RUNS)[r])[0]
    zs = _documented_normals(np.asarray(key), one.num_steps)
    u, x, y, code = _simulate_one(
        setup.diagnoser.dyn, float(one.dt), one.num_steps, plan, setup.signal, zs
    )
    _, out = run.filter_measurements(setup, np.asarray(y), np.asarray(u))
    summary = run.summarize(setup, np.asarray(code), out, runtime_s=1.0)
    return summary, setup.event_steps, np.asarray(x), out["mean"]


def test_sweep_matches_loop_of_single_runs(sweep):
    sc = small_scenario()
    N, dt = sc.num_steps, sc.dt
    faults = list(sc.fault_names)
    assert len(sweep.cells) == 10
    detected_any = false_any = 0
    unexplained_runs = {1.0: 0, 2.0: 0}
    for cell in sweep.cells:
        c = cell.index
        ref_delays = {f: [] for f in faults}
        ref_false = 0
        ref_correct = 0.0
        ref_sq = np.zeros(3)
        ref_nis = 0.0
        for r in range(RUNS):
            s, ev_steps, x, mean = _reference(sc, cell, r)
            # Onsets (drawn in windows) and declarations, run by run.
            for ev, k in zip(s["events"], ev_steps, strict=True):
                assert sweep.onset_step[c, r, faults.index(ev["fault"])] == k
            want_decl = np.full(len(faults), -1)
            for dcl in s["declarations"]:
                want_decl[faults.index(dcl["fault"])] = round(dcl["time"] / dt) - 1
            np.testing.assert_array_equal(sweep.decl_step[c, r], want_decl)
            assert sweep.false_declared()[c, r].sum() == s["false_declarations"]
            assert sweep.correct_samples[c, r] / N == s["mode_accuracy"]
            # The innovation check: the sweep's on-device sum = the single run's summary.
            mean_nis = s["innovation_check"]["mean_nis_per_channel"]
            assert sweep.nis[c, r] / N == pytest.approx(mean_nis, rel=1e-9)
            by = s["innovation_check"]["by_channel"]
            assert list(by) == list(sweep.outputs)
            np.testing.assert_allclose(
                sweep.nis_channels[c, r] / N, [v["mean_nis"] for v in by.values()], rtol=1e-9
            )
            ref_nis += mean_nis
            # Unexplained spells: the first one starts on the same step on the device.
            spells = s["innovation_check"]["unexplained"]
            first = int(sweep.unexplained[c, r])
            assert (first >= 0) == bool(spells)
            if spells:
                assert metrics.sample_time(first + 1, dt) == spells[0]["start"]
                unexplained_runs[cell.noise_scale] += 1
            # TDR, FAR, FIA: accumulated on the device = computed on the host (one definition).
            got = metrics.fdi_rates(metrics.FDICounts(*(a[c, r] for a in sweep.fdi)), N)
            assert (got["tdr"], got["far"]) == (s["tdr"], s["far"])
            if s["fia"] is None:  # nothing detected in this run
                assert got["fia"] is None
            else:
                assert got["fia"] == pytest.approx(s["fia"], rel=1e-9, abs=0)
            for f, delay in s["detection_delay_s"].items():
                got = (
                    sweep.decl_step[c, r, faults.index(f)] - sweep.onset_step[c, r, faults.index(f)]
                )
                if delay is None:
                    assert not sweep.detected()[c, r, faults.index(f)]
                else:
                    assert metrics.sample_time(got, dt) == delay  # rounded to the sample
                    ref_delays[f].append(delay)
            ref_false += s["false_declarations"]
            ref_correct += s["mode_accuracy"] * N
            ref_sq += np.sum((mean - x) ** 2, axis=0)
        # Cell aggregates.
        summ = sweep.summaries[c]
        assert summ["runs"] == RUNS
        assert summ["false_declarations"] == ref_false
        assert summ["mode_accuracy"] == ref_correct / (RUNS * N)
        for f in summ["detection_probability"]:
            assert summ["detection_probability"][f] == len(ref_delays[f]) / RUNS
            med = float(np.median(ref_delays[f])) if ref_delays[f] else None
            assert summ["median_delay_s"][f] == (med and pytest.approx(med, rel=1e-12))
        np.testing.assert_allclose(
            list(summ["state_rmse"].values()), np.sqrt(ref_sq / (RUNS * N)), rtol=1e-9
        )
        assert summ["mean_nis_per_channel"] == pytest.approx(ref_nis / RUNS, rel=1e-9)
        assert summ["runs_unexplained"] == int(np.sum(sweep.unexplained[c] >= 0))
        np.testing.assert_allclose(
            list(summ["mean_nis_by_output"].values()),
            sweep.nis_channels[c].sum(axis=0) / (RUNS * N),
            rtol=1e-12,
        )
        detected_any += sum(len(v) for v in ref_delays.values())
        false_any += ref_false
    # 0.2 s runs hold two windows of 0.1 s: no spell of three (the next tests make some).
    assert unexplained_runs == {1.0: 0, 2.0: 0}
    # The small sweep exercises both detections and misses.
    assert detected_any > 0
    assert np.any(~sweep.detected() & (sweep.onset_step >= 0))


def test_track_spells_on_the_device_equals_spell_steps():
    """The scan's spell tracker finds each run's first spell on the step the NumPy rule
    does: random chi-square innovations, stretches 3x larger of 2-6 windows, gaps."""
    from uimm_jax.engine.innovation import SpellTracker, spell_steps, track_spells

    rng = np.random.default_rng(5)
    B, w, N, m = 16, 50, 2000, 3
    q = rng.chisquare(m, (N, B))
    obs = np.full((N, B), m)
    for b in range(B):
        a = int(rng.integers(0, N - 6 * w))
        q[a : a + int(rng.integers(2, 7)) * w, b] *= 3.0
    q[300:400, 0] = np.nan
    obs[300:400, 0] = 0

    def body(t, inp):
        k, qk, ok = inp
        return track_spells(t, k, qk, ok, w), None

    t0 = SpellTracker.empty(B, jnp.float64)
    ks = jnp.arange(N, dtype=jnp.int32)
    t, _ = jax.lax.scan(body, t0, (ks, jnp.asarray(q), jnp.asarray(obs)))
    first = np.asarray(t.first)
    flagged = 0
    for b in range(B):
        spells = spell_steps(q[:, b], obs[:, b], w)
        assert first[b] == (spells[0][0] if spells else -1)
        flagged += bool(spells)
    assert 0 < flagged < B


def test_sweep_counts_runs_whose_innovations_the_bank_does_not_explain():
    """0.35 s fault-free runs: with the truth's noise doubled (noise_scale 2) every run has
    an unexplained spell from its first sample, with the filter's own noise none; the cell
    counts them and runs.csv gives each start."""
    from uimm_jax.studies.exports import run_rows

    d = scenario_to_dict(load_scenario(ROOT / "scenarios" / "paper_sim1_tuned.toml"))
    d["duration"] = 0.35
    d["events"] = []
    d["sweep"] = {
        "runs": 2, "seed": SEED, "methods": ["uimm"], "noise_scales": [1.0, 2.0],
        "fault_free": True, "cases": [],
    }  # fmt: skip
    sc = parse_scenario(d, source="small")
    res = mc.run_sweep(sc)
    by_scale = {s["noise_scale"]: s["runs_unexplained"] for s in res.summaries}
    assert by_scale == {1.0: 0, 2.0: 2}
    c2 = next(i for i, s in enumerate(res.summaries) if s["noise_scale"] == 2.0)
    np.testing.assert_array_equal(res.unexplained[c2], [0, 0])
    head, rows = run_rows(res)
    starts = sorted(str(row[head.index("unexplained_s")]) for row in rows)
    assert starts == ["", "", "0.0001", "0.0001"]


def test_cells_and_json_schema(sweep):
    doc = sweep.to_json()
    json.dumps(doc)  # serialisable
    assert doc["runs"] == RUNS and len(doc["cells"]) == 10
    for cell in doc["cells"]:
        for key in (
            "method",
            "magnitude",
            "runs",
            "detection_probability",
            "median_delay_s",
            "false_declarations",
            "isolation_accuracy",
            "mode_accuracy",
            "false_alarm_rate_per_hour",
            "confusion",
            "state_rmse",
            "detection_probability_ci",
        ):
            assert key in cell
        conf = np.array(cell["confusion"]["matrix"])
        # One fault-free period per run, one row entry per event.
        assert conf[0].sum() == RUNS
        events = sum(cell["events"].values())
        assert conf[1:].sum() == events
        if cell["case"] == "fault-free":
            assert cell["magnitude"] == 0.0 and cell["detection_probability"] == {}
            assert cell["fault_free_hours"] == pytest.approx(RUNS * 0.2 / 3600)
            assert cell["isolation_accuracy"] is None


def test_same_seed_same_bits_other_seed_differs(sweep):
    again = mc.run_sweep(small_scenario())
    for name in ("decl_step", "onset_step", "correct_samples", "sq_err", "health"):
        np.testing.assert_array_equal(getattr(again, name), getattr(sweep, name))
    other = mc.run_sweep(small_scenario(), seed=SEED + 1)
    assert not np.array_equal(other.sq_err, sweep.sq_err)


def test_second_sweep_compiles_no_kernel(sweep, caplog):
    import logging

    with jax.log_compiles(True), caplog.at_level(logging.WARNING):
        mc.run_sweep(small_scenario(), seed=SEED + 2)
    compiled = [r.getMessage() for r in caplog.records if "Compiling" in r.getMessage()]
    assert not [m for m in compiled if "_scan_chunk" in m], compiled


def test_compile_options_keep_the_bits(sweep, monkeypatch):
    """The chunk compiled with XLA's defaults gives the sweep's bits (CHUNK_COMPILER_OPTIONS)."""
    from uimm_jax.engine.scan import simulate_diagnose
    from uimm_jax.studies import sweep_batch

    assert sweep_batch.CHUNK_COMPILER_OPTIONS
    plain = jax.jit(simulate_diagnose, static_argnums=(0, 1, 2))
    monkeypatch.setattr(sweep_batch, "_jit_chunk", plain)
    again = mc.run_sweep(small_scenario())
    for name in ("decl_step", "correct_samples", "sq_err", "health"):
        np.testing.assert_array_equal(getattr(again, name), getattr(sweep, name))


def test_sharded_equals_unsharded(sweep, sharded_proc):
    proc, out = sharded_proc
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 0, stderr[-3000:]
    got = np.load(out)
    np.testing.assert_array_equal(got["onset_step"], sweep.onset_step)
    np.testing.assert_array_equal(got["decl_step"], sweep.decl_step)
    np.testing.assert_array_equal(got["correct"], sweep.correct_samples)
    np.testing.assert_array_equal(got["health"], sweep.health)
    np.testing.assert_array_equal(got["sq_err"], sweep.sq_err)


# --------------------------------------------------------------------------------------
# CLI and outputs
# --------------------------------------------------------------------------------------


def test_cli_sweep_writes_results(sweep, tmp_path, capsys):
    from uimm_jax.cli import main
    from uimm_jax.scenario.write import dump_scenario

    path = dump_scenario(small_scenario(), tmp_path / "small.toml")
    out = tmp_path / "out"
    rc = main(["sweep", str(path), "--out", str(out), "--quiet"])
    assert rc == 0
    doc = json.loads((out / "results.json").read_text())
    assert len(doc["cells"]) == 10
    # The CLI run is the same sweep: same numbers.
    for got, want in zip(doc["cells"], sweep.summaries, strict=True):
        assert got["detection_probability"] == want["detection_probability"]
        assert got["mode_accuracy"] == want["mode_accuracy"]
    rows = (out / "results.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 10
    assert len((out / "runs.csv").read_text().strip().splitlines()) == 1 + 10 * RUNS
    for name in ("sweep_sim1.png", "sweep_sim2.png", "confusion_uimm.png"):
        assert (out / name).stat().st_size > 1000
    printed = capsys.readouterr().out
    assert "fault-free" in printed and "run-steps" in printed


def test_runs_csv_one_row_per_run(sweep, tmp_path):
    """runs.csv: one row per run; its declarations and rates agree with the cell metrics."""
    import csv

    from uimm_jax.studies.exports import write_runs_csv

    rows = list(csv.DictReader(write_runs_csv(sweep, tmp_path / "runs.csv").open()))
    assert len(rows) == len(sweep.cells) * RUNS
    faults = sweep.faults
    for row in rows:
        c, r = int(row["cell"]), int(row["run"])
        assert row["method"] == sweep.cells[c].method and row["case"] == sweep.cells[c].case
        key = jax.random.split(jax.random.split(jax.random.PRNGKey(SEED), RUNS)[r])[0]
        assert row["seed"] == str(SEED) and row["noise_key"] == "".join(
            f"{int(w):08x}" for w in key
        )
        for j, f in enumerate(faults):
            on, de = sweep.onset_step[c, r, j], sweep.decl_step[c, r, j]
            assert (row[f"{f}:onset_s"] == "") == (on < 0)
            if on >= 0:
                assert float(row[f"{f}:onset_s"]) == pytest.approx(on * sweep.dt, abs=1e-12)
            assert (row[f"{f}:declared_s"] == "") == (de < 0)
            if de >= 0:
                assert round(float(row[f"{f}:declared_s"]) / sweep.dt) == de + 1
                want = "false" if (on < 0 or de < on) else "correct"
                assert row[f"{f}:declaration"] == want
    # Pooled over a cell's runs, the per-run counts give the cell's rates.
    for summ in sweep.summaries:
        cell_rows = [row for row in rows if int(row["cell"]) == sweep.summaries.index(summ)]
        n_false = sum(row[f"{f}:declaration"] == "false" for row in cell_rows for f in faults)
        assert n_false == summ["false_declarations"]
        acc = np.mean([float(row["mode_accuracy"]) for row in cell_rows])
        assert acc == pytest.approx(summ["mode_accuracy"], rel=1e-12)
    assert {"tdr", "far", "fia"} <= set(sweep.summaries[0])
    assert any(row[f"{f}:declaration"] == "correct" for row in rows for f in faults)
    # The innovation check per run and per cell: noise_scale 2 doubles the truth's process
    # and measurement noise sd, so every channel's NIS is about 4x.
    for c, summ in enumerate(sweep.summaries):
        nis = [float(row["nis"]) for row in rows if int(row["cell"]) == c]
        assert np.mean(nis) == pytest.approx(summ["mean_nis_per_channel"], rel=1e-12)
        flagged = [row["unexplained_s"] != "" for row in rows if int(row["cell"]) == c]
        assert sum(flagged) == summ["runs_unexplained"]
    free = {
        s["noise_scale"]: s["mean_nis_per_channel"]
        for s in sweep.summaries
        if s["case"] == "fault-free"
    }
    assert 0.8 < free[1.0] < 1.25 and 3.5 < free[2.0] / free[1.0] < 4.5


def test_cli_sweep_reports_bad_field(tmp_path, capsys):
    from uimm_jax.cli import main
    from uimm_jax.scenario.write import dump_scenario

    path = dump_scenario(small_scenario({"runs": 0}), tmp_path / "bad.toml")
    assert main(["sweep", str(path), "--quiet"]) == 2
    assert "[sweep].runs" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["sweep_paper.toml", "sweep_magnitude.toml"])
def test_sweep_files_are_in_sync_with_the_tuned_scenarios(name):
    sweep_sc = load_scenario(ROOT / "scenarios" / name)
    sim1 = scenario_to_dict(load_scenario(ROOT / "scenarios" / "paper_sim1_tuned.toml"))
    sim2 = load_scenario(ROOT / "scenarios" / "paper_sim2_tuned.toml")
    mine = scenario_to_dict(sweep_sc)
    for key in ("dt", "plant", "input", "noise", "faults"):
        assert mine[key] == sim1[key], key
    # The same filter settings; the sweeps compare the paper's two methods (UIMM and IMM)
    # while the tuned scenarios run the size-estimating UIMM (docs/faults.md), with its
    # [filter.est] table (which a uimm/imm file may not have).
    assert "est" not in mine["filter"] and "est" in sim1["filter"]
    assert mine["filter"] | {"method": "uimm-est", "est": sim1["filter"]["est"]} == sim1["filter"]
    # Same events, times scaled with the duration.
    scale = mine["duration"] / sim1["duration"]
    for a, b in zip(mine["events"], sim1["events"], strict=True):
        assert (a["fault"], a["time"], a["magnitude"]) == (
            b["fault"],
            b["time"] * scale,
            b["magnitude"],
        )
    spec = sweep_spec(sweep_sc)
    assert spec.fault_free and set(spec.methods) == {"uimm", "imm"}
    cases = {c.name: c.events for c in spec.cases}
    for case, ref in (("sim1", sim1["events"]), ("sim2", scenario_to_dict(sim2)["events"])):
        assert [e.fault for e in cases[case]] == [e["fault"] for e in ref]
        for e, r in zip(cases[case], ref, strict=True):
            assert e.time[0] <= r["time"] * scale <= e.time[1]
            assert e.magnitude == r["magnitude"]
