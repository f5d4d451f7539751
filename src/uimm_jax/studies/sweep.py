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
noise (:func:`uimm_jax.engine.truth.truth_step`, step ``k`` from ``fold_in(noise_key, k)``) and
``draw_key`` the onsets drawn in a window (event ``e`` of a case from
``fold_in(draw_key, e)``).  Run ``r`` of every cell uses the same keys (common random
numbers): cells differ only by what they vary, which sharpens comparisons between methods
and magnitudes.  The same seed gives the same numbers bit for bit, whatever the batch size,
the chunk length and the number of devices (each device's share of a batch is padded to a
multiple of :data:`LANES` runs).  The keys come from
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
communication: the runs are independent).

**Metrics**: :func:`uimm_jax.studies.sweep_outputs.cell_summary` (definitions in
:mod:`uimm_jax.engine.metrics`).
"""

from __future__ import annotations

import functools
import numbers
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine.metrics import RunMetrics, init_est_metrics, init_metrics
from uimm_jax.engine.scan import SimCarry, scan_chunked, simulate_diagnose
from uimm_jax.engine.truth import RAMP_STAIRS, TruthPlan, run_keys
from uimm_jax.engine.uimm_est import UIMMEstDiagnoser
from uimm_jax.scenario.sweep import FAULT_FREE, CaseSpec, SweepSpec, sweep_spec
from uimm_jax.studies.run import RunSetup, setup_scenario
from uimm_jax.studies.sweep_outputs import Cell, SweepResult, cell_summary
from uimm_jax.studies.truth import build_truth_plan

__all__ = ["CHUNK_RUN_STEPS", "LANES", "batch_inputs", "run_batch", "run_sweep"]

CHUNK_RUN_STEPS = 2_000_000
"""Default chunk length: about this many run-steps per chunk (``chunk = 2e6 / batch``).

A chunk keeps the truth's states, measurements and codes of its steps, about 52 bytes per
run-step (float64, 3 states, 3 outputs): ~100 MB with the default."""

LANES = 16
"""Each device's share of a batch is padded to a multiple of this many runs.

The run axis is the engine's innermost axis: XLA CPU compiles the loop over it to SIMD
code (4 doubles a vector, 4 vectors an iteration on AVX2) with a differently rounded scalar
remainder, so a run's numbers would depend on its position in a batch that is not a
multiple of 16 (8 was enough while models were the innermost axis; measured: the 4-device
sweep of the tests differs from the 1-device one in the last bits with 8).  Padding keeps
the numbers bit-identical whatever the batch size and the device count."""


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
            k += (RAMP_STAIRS + 1 if ramp > 0 else 1) + (ev.duration is not None)
        worst = max(worst, k)
    return max(2, 1 + worst)  # at least one padding phase: one compiled shape


def _onset_steps(case: CaseSpec, draw_keys: np.ndarray, dt: float, num_steps: int) -> np.ndarray:
    """Onset step of each event of ``case`` for every run: ``(runs, E)`` int64."""
    R = draw_keys.shape[0]
    out = np.zeros((R, len(case.events)), np.int64)
    with jax.default_device(jax.devices("cpu")[0]):
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


def _broadcast_state(state, B: int):
    """A single-run :class:`~uimm_jax.engine.uimm.DiagState` repeated over ``B`` runs.

    Every leaf gains the run axis last (the engine's layout: small axes, models, runs).
    """
    return jax.tree.map(lambda a: jnp.broadcast_to(a[..., None], a.shape + (B,)), state)


def batch_inputs(
    setup: RunSetup,
    onset,
    magnitude,
    noise_scale,
    keys,
    num_phases: int,
    dtype,
    ramp=None,
    end=None,
) -> tuple[TruthPlan, jax.Array, SimCarry]:
    """Truth plan, noise keys and initial carry of one batch of ``B`` runs.

    Args:
        setup: the method's :class:`~uimm_jax.studies.run.RunSetup`.
        onset: ``(B, F)`` onset step of each fault (``-1``: absent).
        magnitude: ``(B, F)`` truth magnitude of each fault.
        noise_scale: ``(B,)`` scale of each run's truth noise.
        keys: ``(B, 2)`` noise keys (:func:`~uimm_jax.engine.truth.run_keys`).
        num_phases: phases per run (one compiled shape for every batch).
        dtype: float dtype.
        ramp: optional ``(B, F)`` ramp steps of each fault.
        end: optional ``(B, F)`` end step of each fault (-1: never).
    """
    scenario = setup.scenario
    B = len(keys)
    plan = build_truth_plan(
        scenario,
        setup.diagnoser.dyn,
        setup.table,
        onset,
        magnitude,
        dtype=dtype,
        num_phases=num_phases,
        noise_scale=noise_scale,
        ramp=ramp,
        end=end,
        where="[sweep]: ",
        hint="the magnitudes and the fault values",
    )
    n = scenario.plant.state_dim
    carry = SimCarry(
        x=jnp.zeros((n, B), dtype),
        diag=_broadcast_state(setup.init_state, B),
        metrics=init_metrics(B, scenario.num_faults, n, dtype),
        est=(
            init_est_metrics(B, scenario.num_faults, dtype)
            if isinstance(setup.diagnoser, UIMMEstDiagnoser)
            else None
        ),
    )
    return plan, jnp.asarray(keys), carry


_jit_chunk = jax.jit(simulate_diagnose, static_argnums=(0, 1, 2))


def _run_spec(ndim: int, trailing: int):
    from jax.sharding import PartitionSpec

    lead = ndim - 1 - trailing
    return PartitionSpec(*([None] * lead), "runs", *([None] * trailing))


def _specs(carry: SimCarry, plan: TruthPlan, keys):
    """PartitionSpecs that split the run axis of every batched leaf.

    The run axis is the last axis of the carry's leaves (the engine's layout: small axes,
    models, runs) and the one before the last of the truth plan's phase leaves
    (``(..., runs, phases)``) and of the keys.
    """

    def t(tree, trailing):
        return jax.tree.map(lambda a: _run_spec(a.ndim, trailing), tree)

    carry_spec = t(carry, 0)
    plan_spec = TruthPlan(
        cache=t(plan.cache, 1),
        event_steps=t(plan.event_steps, 1),
        true_codes=t(plan.true_codes, 1),
        Gq=t(plan.Gq, 0),
        Gr=t(plan.Gr, 0),
    )
    return carry_spec, plan_spec, t(keys, 1)


@functools.lru_cache(maxsize=32)
def _sharded_chunk(diag, dt, p, mesh, carry_spec, plan_spec, keys_spec):
    """A jitted, shard_mapped chunk function (cached: built and compiled once)."""
    from jax.sharding import PartitionSpec

    rep = PartitionSpec()

    def fn(params, plan, signal, keys, carry, ks):
        return simulate_diagnose(diag, dt, p, params, plan, signal, keys, carry, ks)

    smap = jax.shard_map(
        fn,
        mesh=mesh,
        in_specs=(rep, plan_spec, rep, keys_spec, carry_spec, rep),
        out_specs=carry_spec,
        check_vma=False,
    )
    return jax.jit(smap)


def _place(tree, specs, mesh):
    from jax.sharding import NamedSharding

    return jax.tree.map(lambda a, s: jax.device_put(a, NamedSharding(mesh, s)), tree, specs)


def _fetch(tree):
    """Host NumPy copies of (possibly sharded, possibly multi-process) arrays."""
    if jax.process_count() > 1:  # pragma: no cover - multi-host only
        from jax.experimental import multihost_utils

        return jax.tree.map(
            lambda a: np.asarray(multihost_utils.process_allgather(a, tiled=True)), tree
        )
    return jax.tree.map(np.asarray, tree)


def run_batch(
    setup: RunSetup,
    plan,
    keys,
    carry,
    num_steps: int,
    chunk: int,
    *,
    mesh=None,
    progress=None,
    est_out: list | None = None,
) -> RunMetrics:
    """Scan one batch over all steps (chunked); return its :class:`RunMetrics` on the host.

    Args:
        setup: the method's :class:`~uimm_jax.studies.run.RunSetup`.
        plan: see :func:`batch_inputs`.
        keys: see :func:`batch_inputs`.
        carry: see :func:`batch_inputs`.
        num_steps: samples per run.
        chunk: time steps per compiled chunk.
        mesh: optional ``jax.sharding.Mesh`` with a ``"runs"`` axis to shard the runs over.
        progress: optional ``(done, total, elapsed)`` callback of :func:`scan_chunked`.
        est_out: optional list; the batch's host
            :class:`~uimm_jax.engine.metrics.EstMetrics` (or ``None``) is appended.
    """
    diag, params, signal = setup.diagnoser, setup.params, setup.signal
    dt, p = float(setup.scenario.dt), setup.scenario.plant.input_dim
    if mesh is None:

        def run(c, k0, ks):
            del k0
            return _jit_chunk(diag, dt, p, params, plan, signal, keys, c, ks), None

    else:
        cs, ps, kspec = _specs(carry, plan, keys)
        fn = _sharded_chunk(diag, dt, p, mesh, cs, ps, kspec)
        carry = _place(carry, cs, mesh)
        plan = _place(plan, ps, mesh)
        keys = _place(keys, kspec, mesh)

        def run(c, k0, ks):
            del k0
            return fn(params, plan, signal, keys, c, ks), None

    carry, _ = scan_chunked(
        run, carry, num_steps, chunk=chunk, progress=progress, keep_outputs=False
    )
    if est_out is not None:
        est_out.append(None if carry.est is None else _fetch(carry.est))
    return _fetch(carry.metrics)


class _Eta:
    """Default progress printer: one updating line on stderr."""

    def __init__(self, total: int):
        self.total = total
        self.t0 = time.perf_counter()

    def __call__(self, label: str, done: int) -> None:
        el = time.perf_counter() - self.t0
        frac = done / max(self.total, 1)
        eta = el / frac - el if frac > 0 else float("nan")
        end = "\n" if done >= self.total else "\r"
        print(
            f"  sweep {label:24s} {100 * frac:5.1f}% ({done:.3g}/{self.total:.3g} run-steps, "
            f"{el:7.1f} s, ETA {eta:7.1f} s)",
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
    if isinstance(devices, numbers.Integral):
        devs = jax.devices()
        if not 1 <= int(devices) <= len(devs):
            raise ValueError(f"devices: expected 1..{len(devs)}, got {devices}")
        return list(devs[: int(devices)])
    return list(devices)


def _report_chunk(report, label, base, B, done, total, elapsed):
    del total, elapsed
    report(label, base + done * B)


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
    progress: bool | Callable[[str, int, int], None] = False,
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
        devices: devices to shard the run axis over: ``None`` (all of ``jax.devices()``),
            a count, or a list of devices.
        dtype: float dtype (default: JAX's default float; enable float64 first).
        progress: ``True`` for a progress line with an ETA on stderr, or a callback
            ``(label, done_run_steps, total_run_steps)``.

    Returns:
        A :class:`SweepResult` with one summary per cell.
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
            last = lasts[case.name][:, e]
            end_arr[cell.index, :, j] = np.where(last > 0, onsets[case.name][:, e] + last, -1)
    K = _max_phases(spec)
    decl_step = np.full((C, R, F), -1, np.int32)
    correct = np.zeros((C, R), np.int64)
    sq_err = np.zeros((C, R, n))
    health = np.zeros((C, R), np.int32)
    est_arr = {
        "retract_step": np.full((C, R, F), -1, np.int32),
        "declarations": np.zeros((C, R, F), np.int32),
        "false_count": np.zeros((C, R), np.int32),
        "magnitude": np.full((C, R, F), np.nan),
        "magnitude_sd": np.full((C, R, F), np.nan),
    }
    any_est = False

    # Batches: as few as ``batch`` allows, of equal sizes, a multiple of LANES per device.
    jobs_per_method = R * (C // len(spec.methods))
    nb = _ceil_div(jobs_per_method, spec.batch)
    B = _ceil_div(_ceil_div(jobs_per_method, nb), LANES * nd) * LANES * nd
    chunk_len = spec.chunk or _even_chunk(N, max(1000, CHUNK_RUN_STEPS // B))
    chunk_len = min(chunk_len, N)
    total = len(spec.methods) * nb * B * N
    if progress is True:
        report = _Eta(total)
    elif callable(progress):
        report = lambda label, done, tot=total: progress(label, done, tot)  # noqa: E731
    else:
        report = None
    t_start = time.perf_counter()
    done_steps = 0
    for method in spec.methods:
        setup = setup_scenario(scenario, method, dtype=dtype)
        jobs = [(c.index, r, c.noise_scale) for c in cells if c.method == method for r in range(R)]
        for b in range(nb):
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
            )
            label = f"{method} batch {b + 1}/{nb}"
            cb = None
            if report is not None:
                cb = functools.partial(_report_chunk, report, label, done_steps, B)
            got: list = []
            m = run_batch(
                setup, plan, keys, carry, N, chunk_len, mesh=mesh, progress=cb, est_out=got
            )
            done_steps += B * N
            c, r = ci[:real], ri[:real]
            decl_step[c, r] = m.decl_step.T[:real]
            correct[c, r] = m.correct[:real]
            sq_err[c, r] = m.sq_err[:, :real].T
            health[c, r] = m.health[:real]
            if got[0] is not None:
                any_est = True
                for name, arr in est_arr.items():
                    v = np.asarray(getattr(got[0], name))
                    arr[c, r] = (v.T if v.ndim == 2 else v)[:real]
    if report is not None and done_steps < total:
        report("done", total)
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
        true_magnitude=mag_arr,
        end_step=end_arr,
        estimates=est_arr if any_est else None,
        runtime_s=time.perf_counter() - t_start,
        devices=nd,
        batch=B,
        chunk=chunk_len,
    )
    result.summaries = [cell_summary(result, c.index) for c in cells]
    return result
