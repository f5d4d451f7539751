"""Multi-process sweeps: two processes on 127.0.0.1 (jax.distributed, CPU, gloo) vs one.

The two processes are ``uimm-jax sweep --coordinator 127.0.0.1:PORT --num-processes 2
--process-id I``, each with one CPU device, so the runs are sharded over two devices in
two processes; process 0 gathers and writes ``runs.npz``.  Its per-run arrays must equal,
bit for bit, those of one process sharding the same sweep over two devices
(``--host-devices 2``, the same batch layout; across layouts the summed squared errors
may differ in the last bits, see docs/montecarlo.md).  The launcher detection (Slurm,
Open MPI) and the argument checks are tested without a cluster.
"""

import json
import os
import socket
import subprocess
import sys

import numpy as np
import pytest
from test_montecarlo import small_scenario

from uimm_jax.scenario.parse import parse_scenario
from uimm_jax.scenario.write import dump_scenario, scenario_to_dict
from uimm_jax.studies import distributed
from uimm_jax.studies import sweep as mc

ARRAYS = ("onset_step", "decl_step", "correct_samples", "sq_err", "health")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cli_env() -> dict:
    env = dict(os.environ)
    env["JAX_PLATFORMS"] = "cpu"
    env.pop("XLA_FLAGS", None)  # one CPU device per process; the CLI adds its flags
    for name in list(env):  # not a cluster launch, whatever runs the tests
        if name.startswith(("SLURM_", "OMPI_")):
            del env[name]
    return env


def uimm_jax(*args: str) -> list[str]:
    return [sys.executable, "-m", "uimm_jax", *args]


def test_two_processes_equal_one_bit_for_bit(tmp_path):
    path = dump_scenario(small_scenario(), tmp_path / "small.toml")
    out, out_one = tmp_path / "out", tmp_path / "one"
    port = free_port()
    one_proc = subprocess.Popen(
        uimm_jax("sweep", str(path), "--out", str(out_one), "--no-plots", "--host-devices", "2"),
        env=cli_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    procs = [
        subprocess.Popen(
            uimm_jax(
                "sweep",
                str(path),
                "--out",
                str(out),
                "--no-plots",
                "--coordinator",
                f"127.0.0.1:{port}",
                "--num-processes",
                "2",
                "--process-id",
                str(i),
            ),
            env=cli_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for i in (0, 1)
    ]
    procs.append(one_proc)
    try:
        logs = [p.communicate(timeout=300) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for p, (_, err) in zip(procs, logs, strict=True):
        assert p.returncode == 0, err[-3000:]
    doc = json.loads((out / "results.json").read_text())
    assert doc["processes"] == 2 and doc["devices"] == 2
    doc_one = json.loads((out_one / "results.json").read_text())
    assert doc_one["processes"] == 1 and doc_one["devices"] == 2
    got, want = np.load(out / "runs.npz"), np.load(out_one / "runs.npz")
    for name in ARRAYS:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    assert got["decl_step"].shape == (10, 2, 3)
    # Process 0 printed the table and the progress in runs over both processes; process 1
    # neither (gloo prints a line of its own).
    (out0, err0), (out1, err1), _ = logs
    assert "fault-free" in out0 and "fault-free" not in out1
    assert "20/20 runs finished over 2 processes" in err0
    assert "runs finished" not in err1


SLURM_STEP = {
    "SLURM_JOB_ID": "4242",
    "SLURM_STEP_ID": "0",
    "SLURM_STEP_NODELIST": "node[001-002]",
    "SLURM_NTASKS": "2",
    "SLURM_STEP_NUM_TASKS": "2",
    "SLURM_PROCID": "1",
    "SLURM_LOCALID": "0",
}


@pytest.mark.parametrize(
    "env, want",
    [
        (SLURM_STEP, "slurm"),
        ({**SLURM_STEP, "SLURM_STEP_NUM_TASKS": "1", "SLURM_NTASKS": "1"}, None),
        # A batch script's own shell: no job step of several tasks.
        ({k: v for k, v in SLURM_STEP.items() if k != "SLURM_STEP_NUM_TASKS"}, None),
        ({k: v for k, v in SLURM_STEP.items() if k != "SLURM_STEP_ID"}, None),
        ({"OMPI_MCA_orte_hnp_uri": "x", "OMPI_COMM_WORLD_SIZE": "4"}, "ompi"),
        ({"OMPI_COMM_WORLD_SIZE": "4"}, None),
        ({"OMPI_MCA_orte_hnp_uri": "x", "OMPI_COMM_WORLD_SIZE": "1"}, None),
        ({}, None),
    ],
)
def test_cluster_launch_detection(env, want):
    assert distributed.cluster_launch(env) == want


@pytest.mark.parametrize(
    "args, words",
    [
        (("127.0.0.1:1234", None, None), "go together"),
        ((None, 2, 0), "go together"),
        (("127.0.0.1", 2, 0), "HOST:PORT"),
        (("127.0.0.1:99999", 2, 0), "HOST:PORT"),
        (("127.0.0.1:1234", 0, 0), "--num-processes"),
        (("127.0.0.1:1234", 2, 2), "--process-id: expected an integer in 0..1"),
    ],
)
def test_initialize_checks_its_arguments(args, words):
    with pytest.raises(ValueError, match=words):
        distributed.initialize(*args, env={})


def test_single_process_stays_single():
    assert distributed.initialize(env={}) is False
    assert distributed.initialize("127.0.0.1:1234", 1, 0, env={}) is False
    assert distributed.is_main()
    tree = {"a": np.arange(3)}
    assert distributed.share(tree) is tree


def test_cli_bad_process_arguments_are_one_line(tmp_path, capsys):
    from uimm_jax.cli import main

    path = dump_scenario(small_scenario(), tmp_path / "small.toml")
    assert main(["sweep", str(path), "--coordinator", "localhost:1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --coordinator, --num-processes and --process-id go together")


@pytest.mark.parametrize(
    "value, words", [("0.5,abc", "'abc' in '0.5,abc' is not a finite number"),
                     ("0.5,,1", "empty item"), ("1,nan", "'nan'")]
)  # fmt: skip
def test_cli_magnitudes_error_names_the_item(value, words, capsys):
    from uimm_jax.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["sweep", "x.toml", "--magnitudes", value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "argument --magnitudes:" in err and words in err
    assert "_floats" not in err


def test_cli_duration_scales_events_and_cases():
    from uimm_jax.cli._args import with_duration

    sc = small_scenario()
    half = with_duration(sc, 0.1, "--duration")
    assert half.num_steps == sc.num_steps // 2
    assert [e.time for e in half.events] == [e.time / 2 for e in sc.events]
    want = [
        [ev["time"] / 2 if not isinstance(ev["time"], list) else [t / 2 for t in ev["time"]]
         for ev in case["events"]]
        for case in sc.sweep["cases"]
    ]  # fmt: skip
    assert [[ev["time"] for ev in case["events"]] for case in half.sweep["cases"]] == want
    assert with_duration(sc, 0.2, "--duration") is sc
    # an end is an event time too: the fault ends at the same place in the shorter run
    d = scenario_to_dict(sc)
    d["events"][0]["end"] = 0.15
    half = with_duration(parse_scenario(d), 0.1, "--duration")
    assert (half.events[0].time, half.events[0].end) == (sc.events[0].time / 2, 0.075)


def test_cli_duration_must_be_positive(tmp_path, capsys):
    from uimm_jax.cli import main

    path = dump_scenario(small_scenario(), tmp_path / "small.toml")
    assert main(["sweep", str(path), "--duration", "-1"]) == 2
    assert "--duration" in capsys.readouterr().err


def test_devices_cannot_be_chosen_in_one_process_of_many(monkeypatch):
    import jax

    monkeypatch.setattr(jax, "process_count", lambda: 2)
    with pytest.raises(ValueError, match="leave devices"):
        mc._devices_for(1 + len(jax.devices()))
