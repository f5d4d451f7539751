"""The command line: one-line errors without tracebacks, warnings, and determinism."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import uimm_jax
from _robustness_helpers import CHUNK, REPO, short_dict, short_scenario, write_short
from uimm_jax import cli
from uimm_jax.engine.uimm_est_types import EstSettings
from uimm_jax.errors import ScenarioError
from uimm_jax.scenario.parse import load_scenario
from uimm_jax.scenario.write import dump_scenario
from uimm_jax.studies.run import run_scenario

MALFORMED_DIR = Path(__file__).resolve().parents[1] / "malformed"
CORPUS = sorted(p for p in MALFORMED_DIR.glob("*.toml") if not p.name.startswith("_"))


def start_cli(*args) -> subprocess.Popen:
    """Start ``python -m uimm_jax ARGS`` in a fresh process (as a user would run it)."""
    return subprocess.Popen(
        [sys.executable, "-m", "uimm_jax", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ),
        cwd=REPO,
    )


def finish(proc: subprocess.Popen, timeout=600) -> subprocess.CompletedProcess:
    out, err = proc.communicate(timeout=timeout)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def run_cli(*args, timeout=600) -> subprocess.CompletedProcess:
    """Run ``python -m uimm_jax ARGS`` to completion."""
    return finish(start_cli(*args), timeout)


def assert_one_line_error(proc_or_err: str, *patterns):
    lines = [ln for ln in proc_or_err.splitlines() if ln.strip()]
    assert "Traceback" not in proc_or_err, proc_or_err
    assert len(lines) == 1 and lines[0].startswith("error: "), proc_or_err
    for p in patterns:
        assert re.search(p, lines[0]), (p, lines[0])


# --------------------------------------------------------------------------------------
# The malformed-scenario corpus
# --------------------------------------------------------------------------------------


def corpus_errors() -> dict[str, ScenarioError]:
    out = {}
    for path in CORPUS:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                load_scenario(path)
            except ScenarioError as err:
                out[path.name] = err
    return out


def test_corpus_has_at_least_30_distinct_defects():
    errors = corpus_errors()
    assert set(errors) == {p.name for p in CORPUS}, "every corpus file must be refused"
    distinct = {(e.field, re.sub(r"\d+(\.\d+)?", "#", e.detail)) for e in errors.values()}
    assert len(CORPUS) >= 30 and len(distinct) >= 30, (len(CORPUS), len(distinct))
    fields = {e.field for e in errors.values() if e.field}
    assert len(fields) >= 30  # the defects are spread over many fields (46)


@pytest.mark.parametrize("path", CORPUS, ids=[p.name for p in CORPUS])
def test_cli_refuses_every_malformed_scenario_in_one_line(path, capsys, monkeypatch):
    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)
    assert cli.main(["run", str(path), "--quiet", "--no-plots", "--out", "unused"]) == 2
    err = capsys.readouterr().err
    assert_one_line_error(err, re.escape(str(path)))
    field = corpus_errors_cache().get(path.name)
    if field:
        assert f": {field}: " in err


_FIELDS: dict[str, str | None] = {}


def corpus_errors_cache() -> dict[str, str | None]:
    if not _FIELDS:
        _FIELDS.update({k: v.field for k, v in corpus_errors().items()})
    return _FIELDS


@pytest.fixture(scope="module")
def short_file(tmp_path_factory):
    return write_short(tmp_path_factory.mktemp("cli") / "short.toml", 1)


def test_cli_errors_in_a_fresh_process(tmp_path, short_file):
    """A few representative failures, exactly as a user sees them (no traceback)."""
    cases = [
        (["run", MALFORMED_DIR / "bad_transition_row_sum.toml"], [r"\[filter\]\.transition"]),
        (["run", MALFORMED_DIR / "unknown_top_key.toml"], [r"Did you mean 'duration'"]),
        (["run", MALFORMED_DIR / "syntax_error.toml"], [r"TOML syntax error"]),
        (
            ["run", short_file, "--seed", "-1"],
            [r"^error: --seed: expected an integer in \[0, 4294967295\], got -1$"],
        ),
        (
            ["run", short_file, "--measurements", tmp_path / "nope.csv"],
            [r"nope\.csv: file not found"],
        ),
    ]
    (tmp_path / "file").write_text("x")
    cases.append((["run", short_file, "--out", tmp_path / "file"], [r"--out: .* is a file"]))
    started = [start_cli(*args, "--quiet", "--no-plots") for args, _ in cases]
    started.append(start_cli("run", short_file, "--method", "ukf"))
    *procs, usage = [finish(p) for p in started]
    for proc, (args, patterns) in zip(procs, cases, strict=True):
        assert proc.returncode == 2, (args, proc.stderr)
        assert_one_line_error(proc.stderr, *patterns)
    assert usage.returncode == 2 and "Traceback" not in usage.stderr
    assert "invalid choice: 'ukf'" in usage.stderr


def test_cli_warns_about_fixed_up_values(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)
    path = write_short(tmp_path / "s.toml", 1)
    text, count = re.subn(
        r"^initial_mode_probs = .*$",
        "initial_mode_probs = [0.4, 0.3, 0.25, 0.25]",  # the paper's eq. (36): sums to 1.2
        path.read_text(),
        flags=re.M,
    )
    assert count == 1
    path.write_text(text)
    args = ["run", str(path), "--quiet", "--no-plots", "--out", str(tmp_path / "o")]
    assert cli.main(args) == 0
    err = capsys.readouterr().err
    assert re.search(r"^warning: .*initial_mode_probs.*sum to 1\.2.*normali", err, re.M), err


# --------------------------------------------------------------------------------------
# Determinism: same seed -> bit-identical results, in Python and through the CLI
# --------------------------------------------------------------------------------------

SUMMARY_KEYS = (
    "declarations",
    "detection_delay_s",
    "false_declarations",
    "mode_accuracy",
    "health",
    "num_steps",
    "seed",
    "transition",
    "initial_mode_probs",
)


def test_same_seed_bit_identical_in_python():
    sc = short_scenario(2)
    a = run_scenario(sc, seed=11, chunk=CHUNK)
    b = run_scenario(sc, seed=11, chunk=CHUNK)
    c = run_scenario(sc, seed=12, chunk=CHUNK)
    for k in ("y", "x", "u", "truth"):
        np.testing.assert_array_equal(a.truth[k], b.truth[k], err_msg=k)
    for k in ("mode_probs", "mean", "recognised", "declared", "health"):
        np.testing.assert_array_equal(a.outputs[k], b.outputs[k], err_msg=k)
    assert not np.array_equal(a.truth["y"], c.truth["y"])  # the seed matters
    # Chunking does not change the result (noise is drawn from fold_in(key, step)).
    d = run_scenario(sc, seed=11, chunk=2_500)  # (5 000 is test_engine's "fresh" length)
    np.testing.assert_array_equal(a.outputs["mode_probs"], d.outputs["mode_probs"])


@pytest.mark.slow
def test_cli_and_python_api_give_identical_summaries(tmp_path, short_file):
    out = tmp_path / "cli"
    proc = run_cli("run", short_file, "--seed", "5", "--no-plots", "--quiet", "--out", out)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    api = run_scenario(load_scenario(short_file), seed=5).summary
    for key in SUMMARY_KEYS:
        assert summary[key] == api[key], key
    assert [d["fault"] for d in summary["declarations"]] == ["valve_wear", "leakage"]


# --------------------------------------------------------------------------------------
# --version and --help
# --------------------------------------------------------------------------------------


def test_version_prints_the_package_version():
    proc = run_cli("--version", timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"uimm-jax {uimm_jax.__version__}"


@pytest.mark.parametrize("command", [[], ["run"], ["sweep"], ["tune"]], ids=str)
def test_help_shows_no_docstring_markup(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main([*command, "--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith("usage: uimm-jax")
    for markup in ("``", ":mod:", ":func:", ":class:", "`"):
        assert markup not in text, (markup, text)


def test_run_prints_sizes_and_retractions_of_uimm_est(tmp_path, capsys, monkeypatch):
    """uimm-est's summary lines: each declaration's size and interval, each retraction."""
    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)  # main() replaces it
    d = short_dict(2, events=(0.3, 0.5))
    d["events"][1]["end"] = 0.8  # air in oil ends: retracted
    path = dump_scenario(d, tmp_path / "s.toml")
    out = tmp_path / "out"
    assert cli.main(["run", str(path), "--no-plots", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "uimm-est" and summary["retractions"]
    # the tuned file's [filter.est]: the defaults and its per-fault floors (as JSON writes
    # them: a per-fault tuple as a list)
    est = EstSettings(post_floor_means=(0.02, 0.02, 0.002))
    assert summary["est_settings"] == json.loads(json.dumps(est._asdict()))
    for dec in summary["declarations"]:
        lo, hi = dec["magnitude_ci"]
        want = f"magnitude {dec['magnitude']:.4g} [{lo:.4g}, {hi:.4g}]"
        assert re.search(rf"declared {dec['fault']}\s+at .*{re.escape(want)}", text), text
    retracted = re.findall(r"retracted (\w+)\s+at\s+([\d.]+) s  \[(ok|FALSE)\]", text)
    assert [(f, float(t), tag) for f, t, tag in retracted] == [
        (r["fault"], round(r["time"], 4), "ok" if r["correct"] else "FALSE")
        for r in summary["retractions"]
    ]
