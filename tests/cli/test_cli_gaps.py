"""The command-line gaps a new user hit (issue 15): flags checked at once, clear messages.

Every ``tune`` flag is refused before any training starts, with the flag named; the
empty paths of ``run``; ``sweep --duration``, ``--magnitudes`` and ``--host-devices``;
measured data shorter than an event; the float32 console line; the tuned file's name
and header; plants with a repeated fault name.
"""

from __future__ import annotations

import re
import time
import warnings

import numpy as np
import pytest

from _robustness_helpers import short_dict, write_short
from uimm_jax import Fault, LinearPlant, cli
from uimm_jax.cli import _args
from uimm_jax.cli import tune as tune_cli
from uimm_jax.errors import UIMMWarning
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import dump_scenario


@pytest.fixture(scope="module")
def short_file(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("gaps")
    return dump_scenario(short_dict(duration=0.01, events=(0.002, 0.004)), tmp / "s.toml")


def one_line_error(capsys, args, pattern):
    t0 = time.perf_counter()
    assert cli.main([str(a) for a in args]) == 2, args
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert err.startswith("error: ") and re.search(pattern, err), (pattern, err)
    return time.perf_counter() - t0


TUNE_CASES = [
    (["--seed", "-1"], r"--seed: expected an integer in \[0, 4294967295\], got -1"),
    (["--eval-seed", str(2**32)], r"--eval-seed: expected an integer in \[0, 4294967295\]"),
    (["--lr", "-0.1"], r"--lr: expected a finite learning rate > 0, got -0\.1"),
    (["--lr", "nan"], r"--lr: .* got nan"),
    (["--weights", "100,10"], r"--weights: expected 3 comma-separated numbers ce,delay,false"),
    (["--weights", "100,10,10,1"], r"--weights: expected 3 .* got 4"),
    (["--weights", "100,nan,10"], r"--weights: delay = nan; expected a finite number >= 0"),
    (["--weights", "100,10,-1"], r"--weights: false = -1\.0; expected a finite number >= 0"),
    (["--weights", "a,1,1"], r"--weights: ce = 'a' is not a number"),
    (["--train-duration", "0"], r"--train-duration: expected a finite number > 0, got 0\.0"),
    (["--train-duration", "-1"], r"--train-duration: expected a finite number > 0"),
    (["--train-duration", "0.00015"], r"--train-duration 0\.00015: .*not an integer number"),
    (["--fault-free-runs", "-1"], r"--fault-free-runs: expected an integer >= 0, got -1"),
    (["--eval-runs", "0"], r"--eval-runs: expected an integer >= 1, got 0"),
    (["--eval-duration", "-1"], r"--eval-duration: expected a finite number > 0"),
    (["--runs", "0"], r"--runs: expected an integer >= 1"),
]


@pytest.mark.parametrize("flags, pattern", TUNE_CASES, ids=lambda v: str(v))
def test_tune_refuses_bad_flags_at_once(short_file, tmp_path, capsys, flags, pattern):
    out = tmp_path / "t.toml"
    seconds = one_line_error(capsys, ["tune", short_file, "--out", out, *flags], pattern)
    assert seconds < 5  # before any compilation or training
    assert not out.exists()


def test_tune_out_and_before_from_are_checked_first(short_file, tmp_path, capsys):
    one_line_error(capsys, ["tune", short_file, "--out", tmp_path], r"--out: .* is a folder")
    one_line_error(capsys, ["tune", short_file, "--out", ""], r"--out: empty path")
    one_line_error(
        capsys, ["tune", short_file, "--out", tmp_path / "t.json"], r"written as TOML.*t\.toml"
    )
    # The folder of --out is created before training (here the run stops at the next check).
    out = tmp_path / "new" / "sub" / "t.toml"
    one_line_error(
        capsys,
        ["tune", short_file, "--out", out, "--before-from", tmp_path / "nope.tune.json"],
        r"--before-from: .*nope\.tune\.json.* is not a file",
    )
    assert out.parent.is_dir()


def test_tune_help_states_the_evaluation_cost(capsys):
    with pytest.raises(SystemExit):
        cli.main(["tune", "--help"])
    text = "".join(capsys.readouterr().out.split())  # argparse wraps "run-steps" at the "-"
    assert "about4e8run-stepspersetting" in text and "--no-eval" in text


def test_tuned_file_header_says_tuned_and_from_what(short_file):
    class Args:
        scenario = str(short_file)
        iters = 7
        structure = "tied"

    sc = load_scenario(short_file)
    header = tune_cli._tuned_header(Args, sc, 0.5, 8, 123)
    assert header.startswith("# Tuned by uimm-jax tune")
    assert str(short_file) in header and repr(sc.name) in header and "seed 123" in header
    assert all(line.startswith("# ") for line in header.splitlines())


def test_run_refuses_empty_paths(short_file, capsys):
    one_line_error(capsys, ["run", short_file, "--out", ""], r"--out: empty path")
    one_line_error(
        capsys, ["run", short_file, "--measurements", "", "--out", "unused"], r"--measurements"
    )
    one_line_error(capsys, ["sweep", short_file, "--out", " "], r"--out: empty path")


def test_sweep_magnitudes_message_names_the_flag(short_file, capsys):
    with pytest.raises(SystemExit):
        cli.main(["sweep", str(short_file), "--magnitudes", "0.5,abc"])
    err = capsys.readouterr().err
    assert "argument --magnitudes: 'abc' in '0.5,abc' is not a finite number" in err
    assert "_floats" not in err


def test_sweep_host_devices_has_an_upper_bound(short_file, capsys):
    one_line_error(
        capsys,
        ["sweep", short_file, "--host-devices", "100000"],
        rf"--host-devices: expected an integer in \[1, {_args.MAX_HOST_DEVICES}\], got 100000",
    )


def test_with_duration_scales_events_and_sweep_onsets():
    d = short_dict(duration=1.0, events=(0.3, 0.6))
    d["sweep"] = {
        "runs": 1,
        "cases": [{"name": "c", "events": [{"fault": "leakage", "time": [0.2, 0.4]}]}],
    }
    sc = parse_scenario(d)
    half = _args.with_duration(sc, 0.5, "--duration")
    assert half.duration == 0.5 and [e.time for e in half.events] == [0.15, 0.3]
    assert half.sweep["cases"][0]["events"][0]["time"] == [0.1, 0.2]
    assert sc.sweep["cases"][0]["events"][0]["time"] == [0.2, 0.4]  # the source is unchanged
    with pytest.raises(ValueError, match=r"^--duration: expected a finite number > 0"):
        _args.with_duration(sc, -1.0, "--duration")
    with pytest.raises(ValueError, match=r"^--duration 0\.00015: .*integer number of samples"):
        _args.with_duration(sc, 0.00015, "--duration")


def test_sweep_duration_flag_and_clean_imm_runs(short_file, tmp_path, capsys):
    """--duration shortens the runs; a sweep over both methods warns nothing."""
    import json

    out = tmp_path / "o"
    args = ["sweep", str(short_file), "--duration", "0.005", "--runs", "1", "--quiet"]
    args += ["--methods", "uimm,imm", "--no-plots", "--out", str(out)]
    with warnings.catch_warnings():
        warnings.simplefilter("error", UIMMWarning)
        assert cli.main(args) == 0
    assert "warning" not in capsys.readouterr().err
    doc = json.loads((out / "results.json").read_text())
    assert doc["num_steps"] == 50 and {c["method"] for c in doc["cells"]} == {"uimm", "imm"}


def test_measured_data_shorter_than_an_event(short_file, tmp_path, capsys):
    from uimm_jax.studies.run import setup_scenario, simulate_scenario

    sc = load_scenario(short_file)  # events at 2 ms and 4 ms, 100 samples
    # the data (the simulated truth's; no filter run of 100 steps to compile) ends at 3 ms
    y = simulate_scenario(setup_scenario(sc))["y"][:30]
    np.save(tmp_path / "y.npy", y)
    args = ["run", str(short_file), "--measurements", str(tmp_path / "y.npy"), "--quiet"]
    assert cli.main([*args, "--no-plots", "--out", str(tmp_path / "o")]) == 0
    printed = capsys.readouterr().out
    assert re.search(r"leakage .* outside the data \(it ends at 0\.003 s\)", printed), printed
    assert "valve_wear" in printed and "leakage" in printed


def test_float32_console_says_float32(tmp_path, capsys):
    # The 1 s short sim 1 of tests/studies/test_float32.py (its float32 kernel is compiled
    # once for both files: a 100-step file compiled its own, ~15 s of CPU).
    args = ["run", str(write_short(tmp_path / "s.toml", 1)), "--float32", "--quiet", "--no-plots"]
    assert cli.main([*args, "--out", str(tmp_path / "o")]) == 0
    printed = capsys.readouterr().out
    assert re.search(r"^scenario .*float32\)$", printed, re.M)
    # 1e4 steps are one chunk (the CLI's chunk is 1e5): no steady-state rate, and the
    # line says so.
    assert re.search(r"^filter runtime .* us/step, compilation included\)$", printed, re.M)
    assert "steady state" not in printed


def test_plant_with_a_repeated_fault_name_is_refused():
    def matrices(p):
        import jax.numpy as jnp

        return jnp.eye(1) * -p["a"], jnp.eye(1), jnp.eye(1), jnp.zeros(1)

    with pytest.raises(ValueError, match=r"fault names .* must be unique; repeated: stuck"):
        LinearPlant(
            name="dup_faults",
            state_names=("x",),
            input_names=("u",),
            output_names=("x",),
            param_names=("a",),
            nominal_values=(1.0,),
            faults=(Fault("stuck", {"a": 2.0}), Fault("stuck", {"a": 3.0})),
            matrices=matrices,
        )
