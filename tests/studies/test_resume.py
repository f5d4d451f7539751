"""Resumable sweeps: SIGKILL at a random point, then ``--resume``, equals an uninterrupted run.

The sweep runs in a subprocess (``uimm-jax sweep``) with three batches of four chunks
(runs of 2e4 samples, so that a chunk lasts long enough for the kill to land in it);
the test reads its progress line and kills it (SIGKILL) at a random batch and chunk, after
a random delay, so the kill falls during a batch (or while a batch file is written).  The
resumed sweep must skip the batches already on disk and give per-run arrays equal, bit
for bit, to a sweep that was never interrupted.  The random choices are printed with any
failure.
"""

import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from test_montecarlo import SWEEP, small_scenario

from uimm_jax.scenario.sweep import sweep_spec
from uimm_jax.scenario.write import dump_scenario
from uimm_jax.studies import sweep as mc
from uimm_jax.studies import sweep_store

ARRAYS = ("onset_step", "decl_step", "correct_samples", "sq_err", "health")
KILL_SWEEP = dict(SWEEP, runs=4, batch=16, chunk=5000)  # 40 runs: 3 batches of 16, 4 chunks


def kill_scenario():
    """The small sweep with runs of 2 s (chunks of ~0.1 s: a kill lands where it aims)."""
    from uimm_jax.cli._args import with_duration

    return with_duration(small_scenario(KILL_SWEEP), 2.0, "--duration")


def cli(*args, cache=None):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    if cache is not None:  # the resumed process loads what the killed one compiled
        env.update(
            JAX_COMPILATION_CACHE_DIR=str(cache),
            JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
            JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="-1",
        )
    return subprocess.Popen(
        [sys.executable, "-m", "uimm_jax", "sweep", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


def kill_at(proc, batch: int, chunk: int, delay: float) -> str:
    """SIGKILL ``proc`` ``delay`` s after its progress shows ``chunk`` chunks of ``batch``."""
    want = f"batch {batch}/3".encode()
    seen = b""
    while proc.poll() is None:
        data = os.read(proc.stderr.fileno(), 4096)
        if not data:
            break
        seen += data
        lines = seen.replace(b"\r", b"\n").split(b"\n")
        hits = [ln for ln in lines if want in ln and b"runs finished" in ln]
        if len(hits) >= chunk:
            time.sleep(delay)
            proc.send_signal(signal.SIGKILL)
            break
    proc.wait(timeout=300)
    return seen.decode(errors="replace")


def test_sigkill_then_resume_equals_uninterrupted(tmp_path):
    rng = random.Random()
    seed = rng.randrange(2**32)
    rng.seed(seed)
    batch = rng.randint(1, 3)  # the last batch: not after its last chunk (it may end first)
    chunk, delay = rng.randint(1, 4 if batch < 3 else 3), rng.uniform(0.0, 0.03)
    where = f"(random seed {seed}: kill in batch {batch} after {chunk} chunks + {delay:.2f} s)"
    sc = kill_scenario()
    path = dump_scenario(sc, tmp_path / "kill.toml")
    out = tmp_path / "out"
    proc = cli(str(path), "--out", str(out), "--no-plots", cache=tmp_path / "xla")
    try:
        log = kill_at(proc, batch, chunk, delay)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL, f"{where}: the sweep was not killed\n{log}"
    store = out / "checkpoint"
    written = sorted(p.name for p in store.glob("batch-*.npz"))
    assert len(written) < 3 and not (out / "runs.npz").exists(), where
    for name in written:  # whole files only (atomic writes)
        with np.load(store / name) as z:
            assert z["cell"].shape == z["run"].shape == z["correct"].shape, where
    # Resume; meanwhile the uninterrupted sweep runs in this process.
    proc = cli(str(path), "--out", str(out), "--no-plots", "--resume", cache=tmp_path / "xla")
    whole = mc.run_sweep(sc, chunk=20_000)  # the same batches, longer chunks
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, f"{where}\n{stderr.decode()[-3000:]}"
    got = np.load(out / "runs.npz")
    for name in ARRAYS:
        np.testing.assert_array_equal(got[name], getattr(whole, name), err_msg=f"{name} {where}")
    # The resumed sweep ran only the runs that were not on disk.
    runs_before = 16 * len(written)
    assert f"{runs_before}/40 runs finished" in stderr.decode() or runs_before == 0, where
    assert len(list(store.glob("batch-*.npz"))) >= 3
    assert json.loads((store / "manifest.json").read_text())["complete"] is True


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished one-batch sweep with a checkpoint (in this process)."""
    out = tmp_path_factory.mktemp("finished")
    sc = small_scenario()
    return sc, out, mc.run_sweep(sc, checkpoint=out)


def test_resume_of_a_finished_sweep_runs_nothing(finished):
    sc, out, first = finished
    again = mc.run_sweep(sc, checkpoint=out, resume=True, chunk=123)
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name))


@pytest.mark.parametrize(
    "change, words",
    [
        (dict(runs=3), "settings.runs (2 then, 3 now)"),
        (dict(seed=8), "settings.seed (7 then, 8 now)"),
        (dict(magnitudes=[1.0]), "settings.magnitudes ([0.6, 1.0] then, [1.0] now)"),
        (dict(methods=["imm"]), "settings.methods"),
        (dict(dtype=np.float32), 'settings.dtype ("float64" then, "float32" now)'),
        (dict(batch=16), "layout.batch (32 then, 16 now)"),
    ],
)
def test_resume_refuses_other_settings_and_names_them(finished, change, words):
    sc, out, _ = finished
    with pytest.raises(ValueError, match="another scenario or other settings") as exc:
        mc.run_sweep(sc, checkpoint=out, resume=True, **change)
    assert words in str(exc.value)


def test_resume_refuses_another_scenario_and_names_the_field(finished):
    from uimm_jax.scenario.parse import parse_scenario
    from uimm_jax.scenario.write import scenario_to_dict

    sc, out, _ = finished
    d = scenario_to_dict(sc)
    d["filter"]["decision"]["hold"] = d["filter"]["decision"]["hold"] + 1
    other = parse_scenario(d, source="other")
    with pytest.raises(ValueError, match=r"scenario\.filter\.decision\.hold \(\d+ then, \d+ now\)"):
        mc.run_sweep(other, checkpoint=out, resume=True)


def with_est(sc, est=(), **values):
    """``sc`` with a ``[filter.est]`` table of ``values`` only (its method is uimm-est);
    with ``est=None``, without the table (the tuned file's)."""
    from uimm_jax.scenario.parse import parse_scenario
    from uimm_jax.scenario.write import scenario_to_dict

    d = scenario_to_dict(sc)
    d["filter"]["est"] = values
    if est is None:
        del d["filter"]["est"]
    return parse_scenario(d, source="est")


def test_resume_refuses_other_est_settings_and_names_them(finished, tmp_path):
    # [filter.est] is part of the scenario the checkpoint records: each differing setting
    # is named (a manifest-level check, no sweep runs), a resumed sweep refuses it too,
    # and a checkpoint made without the table refuses a scenario with one.
    sc, out, _ = finished
    spec, shape = sweep_spec(sc), (10, 2, 3, 3)
    then = sweep_store.manifest_for(with_est(sc, walk=1e-3), spec, np.float64, 32, 1)
    sweep_store.open_store(tmp_path, then, resume=False, shape=shape)
    now = sweep_store.manifest_for(with_est(sc, walk=2e-3), spec, np.float64, 32, 1)
    named = r"scenario\.filter\.est\.walk \(0\.001 then, 0\.002 now\)"
    with pytest.raises(ValueError, match=named):
        sweep_store.open_store(tmp_path, now, resume=True, shape=shape)
    sweep_store.open_store(tmp_path, then, resume=True, shape=shape)  # the same: resumed
    # the finished sweep ran with the tuned file's table (walk 1e-3, the default)
    with pytest.raises(ValueError, match=named):
        mc.run_sweep(with_est(sc, walk=2e-3), checkpoint=out, resume=True)
    bare = sweep_store.manifest_for(with_est(sc, est=None), spec, np.float64, 32, 1)
    sweep_store.open_store(tmp_path / "bare", bare, resume=False, shape=shape)
    with pytest.raises(ValueError, match=r"scenario\.filter\.est \(absent then, \{"):
        sweep_store.open_store(tmp_path / "bare", now, resume=True, shape=shape)


def one_run(**fields):
    """The arrays of one finished run for ``save_batch`` (3 faults, 3 states)."""
    empty = sweep_store.Finished.empty(1, 1, 3, 3)._asdict()
    empty.pop("done")
    return {k: v[0] for k, v in empty.items()} | fields


def test_unfinished_sweep_is_not_overwritten(tmp_path):
    sc = small_scenario()
    shape = (10, 2, 3, 3)
    manifest = sweep_store.manifest_for(sc, sweep_spec(sc), np.float64, 32, 1)
    store, _ = sweep_store.open_store(tmp_path, manifest, resume=False, shape=shape)
    store.save_batch(np.array([0]), np.array([1]), **one_run(correct=np.array([5])))
    (tmp_path / ".batch-00001.npz.123.tmp").write_bytes(b"half a file")
    with pytest.raises(ValueError, match=r"unfinished sweep \(1 runs finished\); continue it"):
        mc.run_sweep(sc, checkpoint=tmp_path)
    _, fin = sweep_store.open_store(tmp_path, manifest, resume=True, shape=shape)
    assert fin.done.sum() == 1 and fin.done[0, 1] and fin.correct[0, 1] == 5
    assert not list(tmp_path.glob(".*.tmp"))  # leftovers of a kill are removed


def test_resume_needs_a_checkpoint(tmp_path):
    with pytest.raises(ValueError, match="holds no sweep to resume"):
        mc.run_sweep(small_scenario(), checkpoint=tmp_path, resume=True)
    with pytest.raises(ValueError, match="checkpoint folder"):
        mc.run_sweep(small_scenario(), resume=True)


class _Stop(Exception):
    pass


EST_SWEEP = dict(SWEEP, runs=10, methods=["uimm-est"], magnitudes=[1.0], noise_scales=[1.0])
EST_SWEEP["batch"] = 16
EST_SWEEP["cases"] = SWEEP["cases"][:1]  # 2 cells x 10 runs: batches of 16 and 4 runs


def test_uimm_est_sweep_interrupted_then_resumed_equals_uninterrupted(tmp_path):
    # The size-estimating method's arrays (sizes, retractions, declaration counts) are in
    # the checkpoint: a sweep stopped in its second batch and resumed gives, bit for bit,
    # the per-run arrays and estimates of a sweep that was never stopped.
    sc = small_scenario(EST_SWEEP)

    def stop_in_batch_2(label, steps, total):
        if "batch 2/2" in label:
            raise _Stop

    with pytest.raises(_Stop):
        mc.run_sweep(sc, checkpoint=tmp_path, progress=stop_in_batch_2)
    assert len(list(tmp_path.glob("batch-*.npz"))) == 1
    seen = []
    resumed = mc.run_sweep(
        sc, checkpoint=tmp_path, resume=True, progress=lambda *a: seen.append(a)
    )
    N = sc.num_steps
    assert seen and seen[0][1] >= 16 * N and all("batch 1/1" in a[0] for a in seen)  # 4 runs
    whole = mc.run_sweep(sc)
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(resumed, name), getattr(whole, name), err_msg=name)
    assert sorted(resumed.estimates) == sorted(whole.estimates)
    for name, arr in whole.estimates.items():
        np.testing.assert_array_equal(resumed.estimates[name], arr, err_msg=name)
    assert np.all(np.isfinite(whole.estimates["magnitude"]))  # every run was sized
    assert resumed.summaries == whole.summaries


def test_uimm_est_sweep_outcomes_do_not_depend_on_the_batch_size():
    # A uimm-est run's numbers depend only on its own key: the 20 runs in 2 batches of 10
    # (batch=16) and in 7 batches of at most 3 (batch=3), each padded to 16 lanes, so with
    # other batch-mates and other rebuild groups, give the same numbers, bit for bit
    # (uimm-est re-centres a run's expansion when that run needs it, not when any run of
    # its batch does).  Both use the one compiled 16-run kernel.
    whole = mc.run_sweep(small_scenario(EST_SWEEP))
    small = mc.run_sweep(small_scenario(dict(EST_SWEEP, batch=3)))
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(small, name), getattr(whole, name), err_msg=name)
    for name, arr in whole.estimates.items():
        np.testing.assert_array_equal(small.estimates[name], arr, err_msg=name)


def test_resume_reads_batches_without_sizes_only_for_sweeps_without_uimm_est(tmp_path):
    # A batch file written before the sizes were checkpointed (no est_* arrays).
    sc = small_scenario()
    for methods, ok in ((["uimm"], True), (["uimm-est"], False)):
        folder = tmp_path / methods[0]
        spec = sweep_spec(sc, methods=methods)
        manifest = sweep_store.manifest_for(sc, spec, np.float64, 32, 1)
        sweep_store.open_store(folder, manifest, resume=False, shape=(10, 2, 3, 3))
        old = {k: v[None] for k, v in one_run(correct=np.array(7)).items() if "est_" not in k}
        np.savez(folder / "batch-00000.npz", cell=np.array([0]), run=np.array([1]), **old)
        if ok:
            _, fin = sweep_store.open_store(folder, manifest, resume=True, shape=(10, 2, 3, 3))
            assert fin.done[0, 1] and fin.correct[0, 1] == 7
            assert np.isnan(fin.est_magnitude[0, 1]).all()
        else:
            with pytest.raises(ValueError, match="is not a batch of this sweep"):
                sweep_store.open_store(folder, manifest, resume=True, shape=(10, 2, 3, 3))
