"""Monte Carlo studies: many seeds, fault magnitudes, onsets and noise levels, per method.

A *sweep* runs a scenario's diagnoser (UIMM and/or the combinatorial IMM) over many
simulated runs and reports how fast and how reliably each fault is detected and isolated.
It is described by the scenario's ``[sweep]`` table (schema in ``docs/montecarlo.md``)
and/or the arguments of :func:`run_sweep`.

**Cells.**  A cell is one ``(method, case, magnitude, noise_scale)``; it holds ``runs``
runs.  A *case* is a list of fault events (fault, onset time or onset window, magnitude);
the scenario's own ``[[events]]`` are the default case, and the fault-free case (no event)
is added unless ``fault_free = false``.  ``magnitude`` multiplies every event's magnitude
(the truth moves that fraction of the nominal -> fault deviation; the bank keeps its own
fault values, so this studies model mismatch); the fault-free cell has magnitude 0.
``noise_scale`` multiplies the standard deviations of the *truth's* process and
measurement noise (the filter keeps the scenario's ``Q`` and ``R``).

**Randomness.**  ``run_keys = jax.random.split(PRNGKey(seed), runs)``; run ``r`` uses
``noise_key, draw_key = jax.random.split(run_keys[r])``: ``noise_key`` drives the truth
noise (:func:`uimm_jax.engine.truth.truth_step`; step ``k`` from Philox counters ``(k, i)``
under ``noise_key``, :func:`uimm_jax.engine.noise.standard_noise`) and
``draw_key`` the onsets drawn in a window (event ``e`` of a case from
``fold_in(draw_key, e)``).  Run ``r`` of every cell uses the same keys (common random
numbers): cells differ only by what they vary, which sharpens comparisons between methods
and magnitudes.  The same seed gives the same numbers bit for bit for the same batch
layout (runs per batch, devices), whatever the chunk length and however the devices are
spread over processes; each device's share of a batch is padded to a multiple of
:data:`LANES` runs.  Across layouts the declarations stay the same, but the summed squared
state errors may move in the last bits (the covariance update picks the Joseph form for
the whole device batch when any run needs it; ``docs/montecarlo.md``).  The keys come from
:func:`uimm_jax.engine.truth.run_keys`, the truth plans from
:func:`uimm_jax.studies.truth.build_truth_plan` (the builder of single runs).

**Kernel.**  For each method, the runs of all its cells are stacked on the run axis of the
batch-minor engine (``runs = (B,)``, no ``vmap``) and cut into equal batches of at most
``batch`` runs.  One jitted function per chunk of time steps
(:func:`uimm_jax.engine.scan.simulate_diagnose`) runs two ``lax.scan``: the
truth of every run (its own phases, onsets, magnitudes and keys; the input is computed
once per step and shared), then the diagnoser step and the metric updates.  The truth's
per-step values live for one chunk only (about 52 bytes per run-step), so memory is
bounded by ``chunk x batch``, whatever the number of samples; the metrics are carried:
per run, the declaration step of each fault, the number of samples whose recognised fault
set equals the truth, the sums of squared state errors and the OR of the health flags.
(One scan holding both the random number generator and the filter bank was measured 3-7x
slower on XLA CPU.)  The run axis is sharded over the devices with ``shard_map`` (no
communication: the runs are independent).  After ``jax.distributed.initialize``
(:mod:`uimm_jax.studies.distributed`) the devices are those of every process: each puts
its share of a batch on its own devices and the metrics are gathered on every process
after each batch.  With ``checkpoint=`` each finished batch is written to disk as it ends
and ``resume=True`` skips those (:mod:`uimm_jax.studies.sweep_store`).

**Metrics**: :func:`uimm_jax.studies.sweep_outputs.cell_summary` (definitions in
:mod:`uimm_jax.engine.metrics`).
"""

from __future__ import annotations

import functools
import numbers
import sys
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine import metrics
from uimm_jax.engine.truth import GROWTH_KINDS, RAMP_SEGMENTS, fault_levels, run_keys
from uimm_jax.engine.uimm_est import UIMMEstDiagnoser
from uimm_jax.errors import UIMMWarning
from uimm_jax.scenario.sweep import FAULT_FREE, CaseSpec, SweepSpec, sweep_spec
from uimm_jax.studies.run import setup_scenario
from uimm_jax.studies.sweep_batch import batch_inputs, run_batch
from uimm_jax.studies.sweep_outputs import Cell, SweepResult, cell_summary
from uimm_jax.studies.sweep_store import Finished, manifest_for, open_store

__all__ = ["CHUNK_RUN_STEPS", "LANES", "batch_inputs", "run_batch", "run_sweep"]

CHUNK_RUN_STEPS = 640_000
"""Default chunk length: about this many run-steps per chunk (``chunk = 6.4e5 / batch``).

A chunk keeps the truth's states, measurements and codes of its steps, about 52 bytes per
run-step (float64, 3 states, 3 outputs), plus its noise draw (48): ~65 MB with the
default.  Measured (benchmarks/README.md, "Monte Carlo throughput", session 8): at the
default batch of 128 on 2 devices, chunks of 5000 steps take 8 % less CPU time per
run-step than the 15625 of the former ``2e6 / batch``, and 2500 slightly more than 5000."""

LANES = 16
"""Each device's share of a batch is padded to a multiple of this many runs.

The run axis is the engine's innermost axis: XLA CPU compiles the loop over it to SIMD
code (4 doubles a vector, 4 vectors an iteration on AVX2) with a differently rounded scalar
remainder, so a run's numbers would depend on its position in a batch that is not a
multiple of 16 (8 was enough while models were the innermost axis; measured: the 4-device
sweep of the tests differs from the 1-device one in the last bits with 8).  Padding keeps a
run's numbers independent of its position in the batch; they may still move in the last
bits with the batch's other runs (see the module doc), so a resumed sweep keeps its
layout."""


def _cells(spec: SweepSpec) -> list[Cell]:
    cells = []
    for method in spec.methods:
        for noise in spec.noise_scales:
            if spec.fault_free:
                cells.append(Cell(len(cells), method, FAULT_FREE, 0.0, noise))
            for case in spec.cases:
                for mag in spec.magnitudes:
                    for ramp in spec.ramps:
                        cells.append(Cell(len(cells), method, case.name, mag, noise, ramp))
    return cells


def _durations(case: CaseSpec, draw_keys: np.ndarray, dt: float) -> np.ndarray:
    """Steps each event of ``case`` lasts for every run: ``(runs, E)`` int64, -1: for good.

    A window's duration is drawn from ``fold_in(draw_key, 1000 + e)`` (independent of the
    onset draws).
    """
    R = draw_keys.shape[0]
    out = np.full((R, len(case.events)), -1, np.int64)
    with jax.default_device(jax.devices("cpu")[0]):
        for e, ev in enumerate(case.events):
            if ev.duration is None:
                continue
            lo, hi = ev.duration
            u = jax.vmap(
                lambda k, e=e: jax.random.uniform(jax.random.fold_in(k, 1000 + e), (), jnp.float64)
            )(jnp.asarray(draw_keys))
            t = lo + (hi - lo) * np.asarray(u, np.float64)
            out[:, e] = np.maximum(np.round(t / dt).astype(np.int64), 1)
    return out


def _max_phases(spec: SweepSpec) -> int:
    """An upper bound on the truth phases of any run (one compiled shape per batch)."""
    worst = 0
    for case in spec.cases:
        ramps = [r for r in spec.ramps if r is not None]
        k = 0
        for ev in case.events:
            ramp = max([ev.ramp] + ramps) if ramps or ev.ramp else 0.0
            k += (RAMP_SEGMENTS + 1 if ramp > 0 else 1) + (ev.duration is not None)
        worst = max(worst, k)
    return max(2, 1 + worst)  # at least one padding phase: one compiled shape


def _onset_steps(case: CaseSpec, draw_keys: np.ndarray, dt: float, num_steps: int) -> np.ndarray:
    """Onset step of each event of ``case`` for every run: ``(runs, E)`` int64."""
    R = draw_keys.shape[0]
    out = np.zeros((R, len(case.events)), np.int64)
    with jax.default_device(jax.local_devices(backend="cpu")[0]):
        for e, ev in enumerate(case.events):
            lo, hi = ev.time
            if hi > lo:
                u = jax.vmap(
                    lambda k, e=e: jax.random.uniform(jax.random.fold_in(k, e), (), jnp.float64)
                )(jnp.asarray(draw_keys))
                t = lo + (hi - lo) * np.asarray(u, np.float64)
            else:
                t = np.full(R, lo)
            out[:, e] = np.clip(np.round(t / dt).astype(np.int64), 0, num_steps - 1)
    return out


class _Eta:
    """Default progress printer: one updating line on stderr.

    It shows the runs finished out of the sweep's total, counted over every process (each
    process runs its share of every batch, so a batch's runs finish together everywhere),
    the share of the run-steps done and an ETA from this session's pace. A ``stage`` label
    (``tune``'s "before" and "after" sweeps) starts every line.
    """

    def __init__(
        self, total_runs: int, resumed: int, num_steps: int, processes: int, stage: str = ""
    ):
        self.total, self.resumed, self.N = total_runs, resumed, num_steps
        self.where = f" over {processes} processes" if processes > 1 else ""
        self.stage = f"{stage}: " if stage else ""
        self.t0 = time.perf_counter()

    def __call__(self, label: str, runs_done: int, steps_done: float) -> None:
        el = time.perf_counter() - self.t0
        frac = steps_done / max(self.total * self.N, 1)
        start = self.resumed / max(self.total, 1)
        pace = (frac - start) / el if el > 0 else 0.0
        eta = 0.0 if frac >= 1 else (1.0 - frac) / pace if pace > 0 else float("nan")
        end = "\n" if runs_done >= self.total else "\r"
        print(
            f"  {self.stage}sweep {label:24s} {runs_done}/{self.total} runs finished{self.where} "
            f"({100 * frac:5.1f}% of run-steps, {el:7.1f} s, ETA {eta:7.1f} s)",
            end=end,
            file=sys.stderr,
            flush=True,
        )


def _even_chunk(num_steps: int, target: int) -> int:
    """The largest divisor of ``num_steps`` in ``[target / 2, target]`` (else ``target``).

    Equal chunks compile once; a shorter last chunk would compile a second time.
    """
    if target >= num_steps:
        return num_steps
    for d in range(target, max(target // 2, 1) - 1, -1):
        if num_steps % d == 0:
            return d
    return target


def _ceil_div(a: int, b: int) -> int:
    return -(-a // b)


def _devices_for(devices) -> list:
    if devices is None:
        return list(jax.devices())
    if jax.process_count() > 1 and devices != len(jax.devices()):
        raise ValueError(
            f"devices: a sweep over {jax.process_count()} processes runs on every device of "
            f"every process ({len(jax.devices())}); leave devices (--devices) unset"
        )
    if isinstance(devices, numbers.Integral):
        devs = jax.devices()
        if not 1 <= int(devices) <= len(devs):
            raise ValueError(f"devices: expected 1..{len(devs)}, got {devices}")
        return list(devs[: int(devices)])
    return list(devices)


def _report_chunk(report, label, runs_done, real, N, done, total, elapsed):
    del total, elapsed
    report(label, runs_done, (runs_done + real * done / N) * N)


def run_sweep(
    scenario,
    *,
    runs: int | None = None,
    magnitudes: Sequence[float] | None = None,
    ramps: Sequence[float] | None = None,
    methods: Sequence[str] | None = None,
    noise_scales: Sequence[float] | None = None,
    fault_free: bool | None = None,
    cases: Sequence[Mapping] | None = None,
    seed: int | None = None,
    batch: int | None = None,
    chunk: int | None = None,
    devices: Any = None,
    dtype: Any = None,
    progress: bool | str | Callable[[str, int, int], None] = False,
    checkpoint: str | Path | None = None,
    resume: bool = False,
) -> SweepResult:
    """Run a Monte Carlo sweep of a scenario (see the module doc for the semantics).

    Arguments left ``None`` come from the scenario's ``[sweep]`` table, then the defaults
    of :func:`sweep_spec`.

    Args:
        scenario: a :class:`~uimm_jax.scenario.spec.Scenario`.
        runs: runs per cell.
        magnitudes: scales of the events' magnitudes.
        ramps: ramp lengths (s) replacing every event's ramp (one cell each).
        methods: ``"uimm"`` and/or ``"imm"``.
        noise_scales: scales of the truth's noise standard deviations.
        fault_free: include the fault-free case.
        cases: fault cases, as ``[sweep].cases`` entries (dicts with ``name`` and
            ``events``).
        seed: root seed.
        batch: runs per compiled batch (the batches are made equal, with each device's
            share rounded up to a multiple of :data:`LANES` = 16 runs).
        chunk: time steps per compiled chunk.
        devices: devices to shard the run axis over: ``None`` (all of ``jax.devices()``:
            every device of every process after ``jax.distributed.initialize``), a count,
            or a list of devices (single process only).
        dtype: float dtype (default: JAX's default float; enable float64 first).
        progress: ``True`` for a progress line with an ETA on stderr (runs finished out
            of the total), a string for the same line starting with that label, or a
            callback ``(label, done_run_steps, total_run_steps)``.
        checkpoint: a folder where each finished batch's per-run arrays are written as
            the sweep goes (:mod:`uimm_jax.studies.sweep_store`).
        resume: continue the sweep recorded in ``checkpoint``: skip its finished runs
            (refused if the scenario or the settings differ).

    Returns:
        A :class:`SweepResult` with one summary per cell (on every process of a
        multi-process sweep).
    """
    spec = sweep_spec(
        scenario,
        runs=runs,
        seed=seed,
        methods=methods,
        magnitudes=magnitudes,
        ramps=ramps,
        noise_scales=noise_scales,
        fault_free=fault_free,
        cases=cases,
        batch=batch,
        chunk=chunk,
    )
    dtype = dtype or jnp.asarray(0.0).dtype
    devs = _devices_for(devices)
    nd = len(devs)
    mesh = None
    if nd > 1:
        from jax.sharding import Mesh

        mesh = Mesh(np.array(devs), ("runs",))
    cells = _cells(spec)
    R = spec.runs
    F = scenario.num_faults
    n = scenario.plant.state_dim
    N = scenario.num_steps
    dt = float(scenario.dt)
    names = scenario.fault_names
    noise_keys, draw_keys = run_keys(spec.seed, R)
    onsets = {c.name: _onset_steps(c, draw_keys, dt, N) for c in spec.cases}
    lasts = {c.name: _durations(c, draw_keys, dt) for c in spec.cases}
    cases_by_name = {c.name: c for c in spec.cases}
    C = len(cells)
    onset_step = np.full((C, R, F), -1, np.int32)
    mag_arr = np.zeros((C, R, F))
    ramp_arr = np.zeros((C, R, F), np.int64)
    end_arr = np.full((C, R, F), -1, np.int64)
    growth_arr = np.zeros((C, R, F), np.int64)
    for cell in cells:
        if cell.case == FAULT_FREE:
            continue
        case = cases_by_name[cell.case]
        for e, ev in enumerate(case.events):
            j = names.index(ev.fault)
            onset_step[cell.index, :, j] = onsets[case.name][:, e]
            mag_arr[cell.index, :, j] = ev.magnitude * cell.magnitude
            ramp_s = ev.ramp if cell.ramp is None else cell.ramp
            ramp_arr[cell.index, :, j] = int(round(ramp_s / dt))
            growth_arr[cell.index, :, j] = GROWTH_KINDS.index(ev.growth)
            last = lasts[case.name][:, e]
            end_arr[cell.index, :, j] = np.where(last > 0, onsets[case.name][:, e] + last, -1)
    # The truth's magnitude at the run's last step (a ramp may not have completed; an
    # ended fault counted as if it had stayed), against which estimates are scored.
    at_end = np.zeros_like(mag_arr)
    for c, r in np.ndindex(C, R):
        args = (onset_step[c, r], mag_arr[c, r], ramp_arr[c, r], None, [N - 1])
        at_end[c, r] = fault_levels(*args, growth=growth_arr[c, r])[0][0]
    K = _max_phases(spec)
    # Batches: as few as ``batch`` allows, of equal sizes, a multiple of LANES per device.
    jobs_per_method = R * (C // len(spec.methods))
    nb = _ceil_div(jobs_per_method, spec.batch)
    B = _ceil_div(_ceil_div(jobs_per_method, nb), LANES * nd) * LANES * nd
    store = None
    if checkpoint is not None:
        manifest = manifest_for(scenario, spec, dtype, B, nd)
        shape = (C, R, F, n, scenario.plant.output_dim)
        store, fin = open_store(checkpoint, manifest, resume=resume, shape=shape)
    elif resume:
        raise ValueError("resume: give the checkpoint folder to resume from")
    else:
        fin = Finished.empty(C, R, F, n, scenario.plant.output_dim)
    decl_step, correct, sq_err, health = fin.decl_step, fin.correct, fin.sq_err, fin.health
    est_arr = {k[4:]: v for k, v in fin._asdict().items() if k.startswith("est_")}
    chunk_len = spec.chunk or _even_chunk(N, max(1000, CHUNK_RUN_STEPS // B))
    chunk_len = min(chunk_len, N)
    runs_done = int(fin.done.sum())
    if progress is True or isinstance(progress, str):
        stage = progress if isinstance(progress, str) else ""
        report = _Eta(C * R, runs_done, N, jax.process_count(), stage)
    elif callable(progress):
        report = lambda label, runs, steps: progress(label, int(steps), C * R * N)  # noqa: E731
    else:
        report = None
    t_start = time.perf_counter()
    ran = 0
    for method in spec.methods:
        jobs = [
            (c.index, r, c.noise_scale)
            for c in cells
            if c.method == method
            for r in range(R)
            if not fin.done[c.index, r]
        ]
        if not jobs:
            continue
        with warnings.catch_warnings():
            # A sweep over methods adapts the filter settings written for the scenario's
            # own method on purpose (docs/montecarlo.md, "Cells"): no warning per method.
            warnings.filterwarnings("ignore", r"\[filter\]\.\w+ is written for", UIMMWarning)
            setup = setup_scenario(scenario, method, dtype=dtype)
        nbm = _ceil_div(len(jobs), B)
        for b in range(nbm):
            part = jobs[b * B : (b + 1) * B]
            real = len(part)
            part = part + [part[-1]] * (B - real)
            ci, ri, noise = (np.array(a) for a in zip(*part, strict=True))
            plan, keys, carry = batch_inputs(
                setup,
                onset_step[ci, ri],
                mag_arr[ci, ri],
                noise,
                noise_keys[ri],
                K,
                dtype,
                ramp=ramp_arr[ci, ri],
                end=end_arr[ci, ri],
                growth=growth_arr[ci, ri],
            )
            label = f"{method} batch {b + 1}/{nbm}"
            cb = None
            if report is not None:
                cb = functools.partial(_report_chunk, report, label, runs_done, real, N)
            est_got: list = []
            m = run_batch(
                setup, plan, keys, carry, N, chunk_len, mesh=mesh, progress=cb, est_out=est_got
            )
            c, r = ci[:real], ri[:real]
            got = dict(
                decl_step=m.decl_step.T[:real],
                correct=m.correct[:real],
                sq_err=m.sq_err[:, :real].T,
                health=m.health[:real],
                **{f"fdi_{k}": v[:real] for k, v in m.fdi._asdict().items()},
                nis=m.nis[:real],
                unexplained=m.spells.first[:real],
                nis_channels=m.nis_channels.T[:real],
            )
            for name, value in got.items():
                getattr(fin, name)[c, r] = value
            if est_got and est_got[0] is not None:
                for name, arr in est_arr.items():
                    v = np.asarray(getattr(est_got[0], name))
                    arr[c, r] = (v.T if v.ndim == 2 else v)[:real]
            if store is not None:
                store.save_batch(c, r, **got, **{f"est_{k}": v[c, r] for k, v in est_arr.items()})
            runs_done += real
            ran += real
            if report is not None:
                report(label, runs_done, runs_done * N)
    if store is not None:
        store.write_manifest(complete=True)
    if report is not None and ran == 0:  # everything was resumed
        report("resumed", runs_done, runs_done * N)
    fdi = metrics.FDICounts(
        fin.fdi_faulty, fin.fdi_flagged_faulty, fin.fdi_flagged_free, fin.fdi_true_prob
    )
    result = SweepResult(
        spec=spec,
        cells=cells,
        faults=tuple(names),
        states=tuple(scenario.plant.state_names),
        dt=dt,
        num_steps=N,
        scenario=scenario.name,
        source=str(scenario.source),
        onset_step=onset_step,
        decl_step=decl_step,
        correct_samples=correct,
        sq_err=sq_err,
        health=health,
        fdi=fdi,
        nis=fin.nis,
        unexplained=fin.unexplained,
        nis_channels=fin.nis_channels,
        outputs=tuple(scenario.plant.output_names),
        noise_keys=noise_keys,
        true_magnitude=at_end,
        end_step=end_arr,
        estimates=est_arr if UIMMEstDiagnoser.method in spec.methods else None,
        runtime_s=time.perf_counter() - t_start,
        devices=nd,
        processes=jax.process_count(),
        batch=B,
        chunk=chunk_len,
    )
    result.summaries = [cell_summary(result, c.index) for c in cells]
    return result
