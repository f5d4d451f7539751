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
noise (:func:`uimm_jax.simulate.truth_step`, step ``k`` from ``fold_in(noise_key, k)``) and
``draw_key`` the onsets drawn in a window (event ``e`` of a case from
``fold_in(draw_key, e)``).  Run ``r`` of every cell uses the same keys (common random
numbers): cells differ only by what they vary, which sharpens comparisons between methods
and magnitudes.  The same seed gives the same numbers bit for bit, whatever the batch size,
the chunk length and the number of devices (each device's share of a batch is padded to a
multiple of :data:`LANES` runs).

**Kernel.**  For each method, the runs of all its cells are stacked on the run axis of the
batch-minor engine (``runs = (B,)``, no ``vmap``) and cut into equal batches of at most
``batch`` runs.  One jitted function per chunk of time steps runs two ``lax.scan``: the
truth of every run (its own phases, onsets, magnitudes and keys; the input is computed
once per step and shared), then the diagnoser step and the metric updates.  The truth's
per-step values live for one chunk only (about 52 bytes per run-step), so memory is
bounded by ``chunk x batch``, whatever the number of samples; the metrics are carried:
per run, the declaration step of each fault, the number of samples whose recognised fault
set equals the truth, the sums of squared state errors and the OR of the health flags.
(One scan holding both the random number generator and the filter bank was measured 3-7x
slower on XLA CPU.)  The run axis is sharded over the devices with ``shard_map`` (no
communication: the runs are independent).

**Metrics** (per cell, :func:`cell_summary`; a declaration of fault ``j`` at step ``k`` is
*correct* when ``j`` is present in the truth at ``k``, as in
:func:`uimm_jax.runner.summarize`):

* ``detection_probability[j]``: fraction of the runs with an event of ``j`` in which ``j``
  is correctly declared before the end of the run, with a Wilson 95 % interval;
  ``missed_detections[j]`` is the complement as a count;
* delays (``mean/median/p95/max_delay_s[j]``): declaration step minus onset step, times
  ``dt``, over the detected runs (``p95`` with linear interpolation);
* ``false_declarations``: total number of incorrect declarations in the cell;
  ``false_alarm_rate_per_hour``: declarations made while the truth is fault-free, per hour
  of fault-free operation (the whole of a fault-free run, the time before the first onset
  otherwise);
* confusion matrix (rows: the fault-free period of each run, then each true fault event;
  columns: each fault, then ``none``): for a fault event of ``j`` with onset ``s``, the
  first fault *newly* declared in ``[s, next onset)`` (``[s, end)`` for the last event)
  among the faults absent before ``s``; ties go to ``j`` if it is among them, else to
  the lowest fault index; ``none`` if there is none.  For the fault-free period
  ``[0, first onset)`` it is the first fault declared in it, or ``none`` (a true negative).
  ``isolation_accuracy`` is the diagonal's share of the fault events (Wilson interval);
* ``mode_accuracy``: fraction of all samples of the cell whose recognised fault set equals
  the true one;
* ``state_rmse``: root mean square of the combined estimate's error, per state.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
import math
import numbers
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.filtering import scan_chunked
from uimm_jax.scenario.sweep import FAULT_FREE, CaseSpec, EventDraw, SweepSpec, sweep_spec
from uimm_jax.simulate import (
    TruthPlan,
    finite_phases,
    input_value,
    noise_factor,
    truth_step,
)

__all__ = [
    "CaseSpec",
    "Cell",
    "EventDraw",
    "RunMetrics",
    "SweepResult",
    "SweepSpec",
    "cell_summary",
    "run_keys",
    "run_sweep",
    "sweep_spec",
    "wilson_interval",
    "write_sweep_outputs",
]

CHUNK_RUN_STEPS = 2_000_000
"""Default chunk length: about this many run-steps per chunk (``chunk = 2e6 / batch``).

A chunk keeps the truth's states, measurements and codes of its steps, about 52 bytes per
run-step (float64, 3 states, 3 outputs): ~100 MB with the default."""

LANES = 8
"""Each device's share of a batch is padded to a multiple of this many runs.

XLA CPU compiles the batch-minor kernel to SIMD code for batches that are multiples of 8
runs and to differently rounded code for some small or odd batches (e.g. 4, 9 or 13 runs);
padding keeps the numbers bit-identical whatever the batch size and the device count."""

_NEVER = np.iinfo(np.int32).max  # event step of a padding phase: never reached


# --------------------------------------------------------------------------------------
# Specification
# --------------------------------------------------------------------------------------


class Cell(NamedTuple):
    """One cell of a sweep.

    Attributes:
        index: position in :attr:`SweepResult.cells`.
        method: ``"uimm"`` or ``"imm"``.
        case: the case name (``"fault-free"`` for the fault-free case).
        magnitude: the magnitude scale (0 for the fault-free case).
        noise_scale: the truth noise scale.
    """

    index: int
    method: str
    case: str
    magnitude: float
    noise_scale: float


def _cells(spec: SweepSpec) -> list[Cell]:
    cells = []
    for method in spec.methods:
        for noise in spec.noise_scales:
            if spec.fault_free:
                cells.append(Cell(len(cells), method, FAULT_FREE, 0.0, noise))
            for case in spec.cases:
                for mag in spec.magnitudes:
                    cells.append(Cell(len(cells), method, case.name, mag, noise))
    return cells


# --------------------------------------------------------------------------------------
# Keys, onsets and truth plans
# --------------------------------------------------------------------------------------


def run_keys(seed: int, runs: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-run ``(noise_keys, draw_keys)``, each ``(runs, 2)`` raw uint32 keys.

    ``noise_key, draw_key = jax.random.split(jax.random.split(PRNGKey(seed), runs)[r])``.
    """
    with jax.default_device(jax.devices("cpu")[0]):
        keys = jax.random.split(jax.random.PRNGKey(int(seed)), int(runs))
        both = jax.vmap(jax.random.split)(keys)  # (runs, 2, 2)
        both = np.asarray(both)
    return both[:, 0], both[:, 1]


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


class _Job(NamedTuple):
    """Host description of the truth of one run (one element of a batch)."""

    cell: int
    run: int
    onset: np.ndarray  # (F,) onset step of each fault, -1 if absent
    magnitude: np.ndarray  # (F,) truth magnitude of each fault
    noise_scale: float


def _phases(job: _Job, table, K: int):
    """Thetas ``(K, P)``, codes ``(K,)`` and event steps ``(K-1,)`` of one run."""
    order = [j for j in np.argsort(job.onset, kind="stable") if job.onset[j] >= 0]
    present = np.zeros(table.num_faults, bool)
    thetas = [table.nominal.copy()]
    codes = [0]
    steps = []
    for j in order:
        present[j] = True
        thetas.append(table.theta_numpy(present, job.magnitude))
        codes.append(int(np.sum(present * (1 << np.arange(table.num_faults)))))
        steps.append(int(job.onset[j]))
    while len(thetas) < K:
        thetas.append(thetas[-1])
        codes.append(codes[-1])
        steps.append(_NEVER)
    return np.array(thetas), np.array(codes, np.int32), np.array(steps, np.int32)


_PREPARE_WIDTH = 16  # thetas per eager ``prepare`` call (one compiled shape)


def _phase_caches(dyn, thetas: np.ndarray, dtype) -> Any:
    """Dynamics caches of ``(U, P)`` parameter vectors, leaves ``(..., U)``.

    ``prepare`` runs *eagerly*, as :func:`uimm_jax.runner.setup_scenario` does for the
    truth of a single run (a jitted ``prepare`` may round differently), on blocks of a
    fixed width so that the eager kernels compile once.
    """
    U, P = thetas.shape
    W = _PREPARE_WIDTH
    blocks = []
    for s in range(0, U, W):
        blk = thetas[s : s + W]
        nb = len(blk)
        pad = np.concatenate([blk, np.repeat(blk[-1:], W - nb, axis=0)])
        cache = dyn.prepare(jnp.asarray(pad.T, dtype))
        blocks.append(jax.tree.map(lambda a, nb=nb: np.asarray(a)[..., :nb], cache))
    return jax.tree.map(lambda *a: np.concatenate(a, axis=-1), *blocks)


def _batch_plan(jobs: Sequence[_Job], setup, scenario, K: int, dtype) -> TruthPlan:
    """The truth plan of a batch of runs (phases last, runs before them)."""
    table = setup.table
    th, codes, steps = zip(*(_phases(j, table, K) for j in jobs), strict=True)
    th = np.array(th)  # (B, K, P)
    uniq, idx = np.unique(th.reshape(-1, th.shape[-1]), axis=0, return_inverse=True)
    idx = idx.reshape(th.shape[:2])  # (B, K)
    caches = _phase_caches(setup.diagnoser.dyn, uniq, dtype)
    ok = finite_phases(caches, len(uniq))
    if not ok.all():
        theta = uniq[int(np.argmin(ok))]
        changed = {
            k: float(v)
            for k, v, v0 in zip(scenario.plant.param_names, theta, table.nominal, strict=True)
            if v != v0
        }
        raise ValueError(
            f"{scenario.source}: [sweep]: the truth's discretised dynamics are not finite for "
            f"the parameters {changed}: check the magnitudes and the fault values."
        )
    Gq = noise_factor(scenario.process_noise)
    Gr = noise_factor(scenario.measurement_noise)
    s = np.array([j.noise_scale for j in jobs], np.float64)
    return TruthPlan(
        cache=jax.tree.map(lambda a: jnp.asarray(a[..., idx]), caches),
        event_steps=jnp.asarray(np.array(steps, np.int32).reshape(len(jobs), K - 1)),
        true_codes=jnp.asarray(np.array(codes, np.int32)),
        Gq=jnp.asarray(Gq[..., None] * s, dtype),
        Gr=jnp.asarray(Gr[..., None] * s, dtype),
    )


def _broadcast_state(state, B: int):
    """A single-run :class:`~uimm_jax.engine.uimm.DiagState` repeated over a batch of ``B`` runs."""

    def model_last(a):  # (..., M) -> (..., B, M)
        a = jnp.expand_dims(a, -2)
        return jnp.broadcast_to(a, a.shape[:-2] + (B,) + a.shape[-1:])

    def run_last(a):  # (...) -> (..., B)
        return jnp.broadcast_to(a[..., None], a.shape + (B,))

    return type(state)(
        imm=jax.tree.map(model_last, state.imm),
        cache=jax.tree.map(model_last, state.cache),
        declared=model_last(state.declared),
        run_model=run_last(state.run_model),
        run_len=run_last(state.run_len),
    )


# --------------------------------------------------------------------------------------
# The fused kernel
# --------------------------------------------------------------------------------------


class RunMetrics(NamedTuple):
    """Per-run metrics accumulated in the scan carry (batch ``B``).

    Attributes:
        decl_step: ``(B, F)`` int32 step of the declaration of each fault (-1 if none).
        correct: ``(B,)`` int32 samples whose recognised fault set equals the truth.
        sq_err: ``(n, B)`` sum over steps of the squared combined-estimate error.
        health: ``(B,)`` int32 OR of the per-step health flags.
    """

    decl_step: jax.Array
    correct: jax.Array
    sq_err: jax.Array
    health: jax.Array


class _Carry(NamedTuple):
    x: jax.Array  # (n, B) truth state
    diag: Any  # DiagState
    metrics: RunMetrics


def _scan_chunk(diag, dt, p, params, plan, signal, keys, carry, ks):
    """Simulate then diagnose the steps ``ks`` of a batch; return the new carry.

    Two scans in one compiled function: the truth over the chunk (its per-step states,
    measurements and truth codes are kept for this chunk only), then the diagnoser and
    the metric updates.  (A single scan whose body holds both the random number
    generator and the filter bank was measured 3-7x slower on XLA CPU: its body is not
    compiled into one kernel.)
    """

    def truth(x, k):
        t = k.astype(x.dtype) * dt
        u = input_value(signal, t)
        x, y, code = truth_step(
            diag.dyn, plan, x, k, jnp.full((p,) + x.shape[1:], u, x.dtype), keys
        )
        return x, (u, x, y, code)

    x_end, (us, xs, ys, codes) = jax.lax.scan(truth, carry.x, ks)

    def diagnose(c, inp):
        k, u, x, y, code = inp
        u = jnp.full((p,) + x.shape[1:], u, x.dtype)
        st, info = diag.step(c.diag, params, u, y, with_cov=False)
        m = c.metrics
        newly = st.declared & ~c.diag.declared
        err = info.step.mean - x
        m = RunMetrics(
            decl_step=jnp.where(newly, k, m.decl_step),
            correct=m.correct + (info.recognised == code).astype(jnp.int32),
            sq_err=m.sq_err + err * err,
            health=m.health | info.step.health,
        )
        return _Carry(c.x, st, m), None

    carry, _ = jax.lax.scan(diagnose, carry, (ks, us, xs, ys, codes))
    return carry._replace(x=x_end)


_jit_chunk = jax.jit(_scan_chunk, static_argnums=(0, 1, 2))


def _run_spec(ndim: int, trailing: int):
    from jax.sharding import PartitionSpec

    lead = ndim - 1 - trailing
    return PartitionSpec(*([None] * lead), "runs", *([None] * trailing))


def _specs(carry: _Carry, plan: TruthPlan, keys):
    """PartitionSpecs that split the run axis of every batched leaf.

    The run axis is the last axis of per-run leaves (``(..., runs)``) and the one before
    the last of bank and phase leaves (``(..., runs, models)``, ``(..., runs, phases)``).
    """

    def t(tree, trailing):
        return jax.tree.map(lambda a: _run_spec(a.ndim, trailing), tree)

    d = carry.diag
    diag_spec = type(d)(
        imm=t(d.imm, 1),
        cache=t(d.cache, 1),
        declared=t(d.declared, 1),
        run_model=t(d.run_model, 0),
        run_len=t(d.run_len, 0),
    )
    m = carry.metrics
    carry_spec = _Carry(
        x=t(carry.x, 0),
        diag=diag_spec,
        metrics=RunMetrics(t(m.decl_step, 1), t(m.correct, 0), t(m.sq_err, 0), t(m.health, 0)),
    )
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
        return _scan_chunk(diag, dt, p, params, plan, signal, keys, carry, ks)

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


# --------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------


@dataclasses.dataclass
class SweepResult:
    """Everything a sweep produced, as arrays per cell (``C`` cells, ``R`` runs).

    Attributes:
        spec: the :class:`SweepSpec`.
        cells: the :class:`Cell` list.
        faults: fault names (bank order).
        states: state names.
        dt: sample time, s.
        num_steps: samples per run.
        scenario: the scenario's name.
        source: the scenario's source.
        onset_step: ``(C, R, F)`` onset step of each fault (-1: no event).
        decl_step: ``(C, R, F)`` declaration step of each fault (-1: never declared).
        correct_samples: ``(C, R)`` samples with the correct recognised fault set.
        sq_err: ``(C, R, n)`` summed squared state errors.
        health: ``(C, R)`` OR of the health flags.
        summaries: one dict per cell (:func:`cell_summary`).
        runtime_s: wall time of the simulations (compilation included).
        devices: number of devices the run axis was sharded over.
        batch: runs per compiled batch actually used.
        chunk: time steps per compiled chunk actually used.
    """

    spec: SweepSpec
    cells: list[Cell]
    faults: tuple[str, ...]
    states: tuple[str, ...]
    dt: float
    num_steps: int
    scenario: str
    source: str
    onset_step: np.ndarray
    decl_step: np.ndarray
    correct_samples: np.ndarray
    sq_err: np.ndarray
    health: np.ndarray
    summaries: list[dict] = dataclasses.field(default_factory=list)
    runtime_s: float = 0.0
    devices: int = 1
    batch: int = 0
    chunk: int = 0

    @property
    def run_steps(self) -> int:
        """Total number of simulated run-steps."""
        return len(self.cells) * self.spec.runs * self.num_steps

    def detected(self) -> np.ndarray:
        """``(C, R, F)`` bool: the fault occurred and was correctly declared."""
        return (self.onset_step >= 0) & (self.decl_step >= self.onset_step)

    def isolated(self) -> np.ndarray:
        """``(C, R)`` bool: every fault event of the run isolated (confusion diagonal)."""
        on, de, N = self.onset_step, self.decl_step, self.num_steps
        out = np.ones(on.shape[:2], bool)
        for c in range(on.shape[0]):
            for r in range(on.shape[1]):
                conf = _confusion(on[c, r][None], de[c, r][None], N)
                out[c, r] = np.trace(conf[1:, :-1]) == conf[1:].sum()
        return out

    def false_declared(self) -> np.ndarray:
        """``(C, R, F)`` bool: the fault was declared while absent from the truth."""
        d = self.decl_step
        return (d >= 0) & ((self.onset_step < 0) | (d < self.onset_step))

    def to_json(self) -> dict:
        """The ``results.json`` document."""
        s = self.spec
        return {
            "scenario": self.scenario,
            "source": self.source,
            "faults": list(self.faults),
            "states": list(self.states),
            "dt": self.dt,
            "num_steps": self.num_steps,
            "duration_s": self.num_steps * self.dt,
            "seed": s.seed,
            "runs": s.runs,
            "methods": list(s.methods),
            "magnitudes": list(s.magnitudes),
            "noise_scales": list(s.noise_scales),
            "cases": [
                {
                    "name": c.name,
                    "events": [
                        {"fault": e.fault, "time": list(e.time), "magnitude": e.magnitude}
                        for e in c.events
                    ],
                }
                for c in s.cases
            ],
            "fault_free": s.fault_free,
            "batch": self.batch,
            "chunk": self.chunk,
            "devices": self.devices,
            "run_steps": self.run_steps,
            "runtime_s": self.runtime_s,
            "run_steps_per_s": self.run_steps / self.runtime_s if self.runtime_s > 0 else None,
            "cells": self.summaries,
        }


def wilson_interval(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float] | None:
    """Wilson score interval of a binomial proportion ``k / n`` (95 % by default).

    Returns ``None`` when ``n == 0``.
    """
    if n <= 0:
        return None
    p = k / n
    z2 = z * z
    den = 1.0 + z2 / n
    centre = (p + z2 / (2 * n)) / den
    half = z / den * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    return (max(0.0, centre - half), min(1.0, centre + half))


def _confusion(onset: np.ndarray, decl: np.ndarray, num_steps: int) -> np.ndarray:
    """Confusion counts ``(1 + F, F + 1)`` of a set of runs (see the module doc)."""
    R, F = onset.shape
    mat = np.zeros((1 + F, F + 1), np.int64)
    for r in range(R):
        on, de = onset[r], decl[r]
        starts = sorted({int(s) for s in on if s >= 0})
        first = starts[0] if starts else num_steps
        # Fault-free period [0, first).
        cand = [(int(de[f]), f) for f in range(F) if 0 <= de[f] < first]
        mat[0, min(cand)[1] if cand else F] += 1
        for j in range(F):
            s = int(on[j])
            if s < 0:
                continue
            later = [t for t in starts if t > s]
            end = later[0] if later else num_steps
            cand = [
                (int(de[f]), f)
                for f in range(F)
                if not (0 <= on[f] < s) and s <= de[f] < end  # absent before s, declared in
            ]
            if not cand:
                col = F
            else:
                t0 = min(c[0] for c in cand)
                tied = [f for t, f in cand if t == t0]
                col = j if j in tied else min(tied)
            mat[1 + j, col] += 1
    return mat


def _stat(x: np.ndarray, fn) -> float | None:
    return float(fn(x)) if x.size else None


def cell_summary(result: SweepResult, index: int) -> dict:
    """The metrics of one cell (a ``results.json`` cell; see the module doc)."""
    cell = result.cells[index]
    dt = result.dt
    N = result.num_steps
    on = result.onset_step[index]
    de = result.decl_step[index]
    R = on.shape[0]
    faults = result.faults
    det = result.detected()[index]
    false = result.false_declared()[index]
    dp, ci, ndet, nev, missed = {}, {}, {}, {}, {}
    mean_d, med_d, p95_d, max_d = {}, {}, {}, {}
    for j, f in enumerate(faults):
        ev = on[:, j] >= 0
        n = int(ev.sum())
        if n == 0:
            continue
        k = int(det[:, j].sum())
        nev[f], ndet[f], missed[f] = n, k, n - k
        dp[f] = k / n
        ci[f] = list(wilson_interval(k, n))
        d = (de[det[:, j], j] - on[det[:, j], j]).astype(np.float64) * dt
        mean_d[f] = _stat(d, np.mean)
        med_d[f] = _stat(d, np.median)
        p95_d[f] = _stat(d, lambda a: np.percentile(a, 95))
        max_d[f] = _stat(d, np.max)
    first_onset = np.where(on >= 0, on, N).min(axis=1)  # (R,)
    ff_steps = int(first_onset.sum())
    ff_hours = ff_steps * dt / 3600.0
    ff_false = int(np.sum((de >= 0) & (de < first_onset[:, None])))
    conf = _confusion(on, de, N)
    n_events = int(conf[1:].sum())
    iso_k = int(np.trace(conf[1:, :-1]))
    runs_false = int(np.any(false, axis=1).sum())
    sq = result.sq_err[index]  # (R, n)
    rmse = np.sqrt(sq.sum(axis=0) / (R * N))
    health = result.health[index]
    return {
        "method": cell.method,
        "case": cell.case,
        "magnitude": cell.magnitude,
        "noise_scale": cell.noise_scale,
        "runs": R,
        "num_steps": N,
        "events": nev,
        "detections": ndet,
        "detection_probability": dp,
        "detection_probability_ci": ci,
        "missed_detections": missed,
        "mean_delay_s": mean_d,
        "median_delay_s": med_d,
        "p95_delay_s": p95_d,
        "max_delay_s": max_d,
        "false_declarations": int(false.sum()),
        "runs_with_false_declaration": runs_false,
        "false_declaration_run_probability_ci": list(wilson_interval(runs_false, R)),
        "false_declarations_fault_free": ff_false,
        "fault_free_hours": ff_hours,
        "false_alarm_rate_per_hour": ff_false / ff_hours if ff_hours > 0 else None,
        "isolation_accuracy": iso_k / n_events if n_events else None,
        "isolation_accuracy_ci": list(wilson_interval(iso_k, n_events)) if n_events else None,
        "confusion": {
            "rows": ["fault-free"] + list(faults),
            "columns": list(faults) + ["none"],
            "matrix": conf.tolist(),
        },
        "mode_accuracy": float(result.correct_samples[index].sum()) / (R * N),
        "mode_accuracy_min_run": float(result.correct_samples[index].min()) / N,
        "state_rmse": {s: float(v) for s, v in zip(result.states, rmse, strict=True)},
        "health": {
            "runs_cov_repaired": int(np.sum(health & 1 > 0)),
            "runs_nonfinite_caught": int(np.sum(health & 2 > 0)),
            "runs_gated": int(np.sum(health & 4 > 0)),
        },
    }


# --------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------


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


def _make_batch(setup, scenario, jobs: Sequence[_Job], noise_keys: np.ndarray, K: int, dtype):
    """Truth plan, noise keys and initial carry of one batch of runs."""
    B = len(jobs)
    n = scenario.plant.state_dim
    F = scenario.num_faults
    plan = _batch_plan(jobs, setup, scenario, K, dtype)
    keys = jnp.asarray(np.stack([noise_keys[j.run] for j in jobs]))
    carry = _Carry(
        x=jnp.zeros((n, B), dtype),
        diag=_broadcast_state(setup.init_state, B),
        metrics=RunMetrics(
            decl_step=jnp.full((B, F), -1, jnp.int32),
            correct=jnp.zeros((B,), jnp.int32),
            sq_err=jnp.zeros((n, B), dtype),
            health=jnp.zeros((B,), jnp.int32),
        ),
    )
    return plan, keys, carry


def _report_chunk(report, label, base, B, done, total, elapsed):
    del total, elapsed
    report(label, base + done * B)


def _run_batch(diag, dt, p, params, signal, plan, keys, carry, mesh, num_steps, chunk, progress):
    """Scan one batch over all steps (chunked); return its :class:`RunMetrics` on the host."""
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
    return _fetch(carry.metrics)


def run_sweep(
    scenario,
    *,
    runs: int | None = None,
    magnitudes: Sequence[float] | None = None,
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
        scenario: a :class:`~uimm_jax.scenarios.Scenario`.
        runs: runs per cell.
        magnitudes: scales of the events' magnitudes.
        methods: ``"uimm"`` and/or ``"imm"``.
        noise_scales: scales of the truth's noise standard deviations.
        fault_free: include the fault-free case.
        cases: fault cases, as ``[sweep].cases`` entries (dicts with ``name`` and
            ``events``).
        seed: root seed.
        batch: runs per compiled batch (the batches are made equal, with each device's
            share rounded up to a multiple of :data:`LANES` = 8 runs).
        chunk: time steps per compiled chunk.
        devices: devices to shard the run axis over: ``None`` (all of ``jax.devices()``),
            a count, or a list of devices.
        dtype: float dtype (default: JAX's default float; enable float64 first).
        progress: ``True`` for a progress line with an ETA on stderr, or a callback
            ``(label, done_run_steps, total_run_steps)``.

    Returns:
        A :class:`SweepResult` with one summary per cell.
    """
    from uimm_jax.runner import setup_scenario

    spec = sweep_spec(
        scenario,
        runs=runs,
        seed=seed,
        methods=methods,
        magnitudes=magnitudes,
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
    p = scenario.plant.input_dim
    N = scenario.num_steps
    dt = float(scenario.dt)
    names = scenario.fault_names
    noise_keys, draw_keys = run_keys(spec.seed, R)
    onsets = {c.name: _onset_steps(c, draw_keys, dt, N) for c in spec.cases}
    cases_by_name = {c.name: c for c in spec.cases}
    C = len(cells)
    onset_step = np.full((C, R, F), -1, np.int32)
    mag_arr = np.zeros((C, R, F))
    for cell in cells:
        if cell.case == FAULT_FREE:
            continue
        case = cases_by_name[cell.case]
        for e, ev in enumerate(case.events):
            j = names.index(ev.fault)
            onset_step[cell.index, :, j] = onsets[case.name][:, e]
            mag_arr[cell.index, :, j] = ev.magnitude * cell.magnitude
    K = 1 + max((len(c.events) for c in spec.cases), default=0)
    K = max(K, 2)  # at least one (padding) event: one compiled shape for every batch
    decl_step = np.full((C, R, F), -1, np.int32)
    correct = np.zeros((C, R), np.int64)
    sq_err = np.zeros((C, R, n))
    health = np.zeros((C, R), np.int32)

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
        diag = setup.diagnoser
        jobs = [
            _Job(c.index, r, onset_step[c.index, r], mag_arr[c.index, r], c.noise_scale)
            for c in cells
            if c.method == method
            for r in range(R)
        ]
        for b in range(nb):
            part = jobs[b * B : (b + 1) * B]
            real = len(part)
            part = part + [part[-1]] * (B - real)
            plan, keys, carry = _make_batch(setup, scenario, part, noise_keys, K, dtype)
            label = f"{method} batch {b + 1}/{nb}"
            cb = None
            if report is not None:
                cb = functools.partial(_report_chunk, report, label, done_steps, B)
            m = _run_batch(
                diag, dt, p, setup.params, setup.signal, plan, keys, carry, mesh, N, chunk_len, cb
            )
            done_steps += B * N
            for i, job in enumerate(part[:real]):
                decl_step[job.cell, job.run] = m.decl_step[i]
                correct[job.cell, job.run] = m.correct[i]
                sq_err[job.cell, job.run] = m.sq_err[:, i]
                health[job.cell, job.run] = m.health[i]
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
        runtime_s=time.perf_counter() - t_start,
        devices=nd,
        batch=B,
        chunk=chunk_len,
    )
    result.summaries = [cell_summary(result, c.index) for c in cells]
    return result


# --------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------


def _csv_rows(result: SweepResult) -> tuple[list[str], list[list]]:
    faults = result.faults
    head = ["method", "case", "magnitude", "noise_scale", "runs"]
    for f in faults:
        head += [
            f"{f}:events",
            f"{f}:detection_probability",
            f"{f}:detection_ci_lo",
            f"{f}:detection_ci_hi",
            f"{f}:missed",
            f"{f}:mean_delay_s",
            f"{f}:median_delay_s",
            f"{f}:p95_delay_s",
            f"{f}:max_delay_s",
        ]
    head += [
        "false_declarations",
        "runs_with_false_declaration",
        "false_declarations_fault_free",
        "fault_free_hours",
        "false_alarm_rate_per_hour",
        "isolation_accuracy",
        "mode_accuracy",
    ] + [f"rmse:{s}" for s in result.states]
    rows = []
    for s in result.summaries:
        row = [s["method"], s["case"], s["magnitude"], s["noise_scale"], s["runs"]]
        for f in faults:
            ci = s["detection_probability_ci"].get(f) or [None, None]
            row += [
                s["events"].get(f, 0),
                s["detection_probability"].get(f),
                ci[0],
                ci[1],
                s["missed_detections"].get(f),
                s["mean_delay_s"].get(f),
                s["median_delay_s"].get(f),
                s["p95_delay_s"].get(f),
                s["max_delay_s"].get(f),
            ]
        row += [
            s["false_declarations"],
            s["runs_with_false_declaration"],
            s["false_declarations_fault_free"],
            s["fault_free_hours"],
            s["false_alarm_rate_per_hour"],
            s["isolation_accuracy"],
            s["mode_accuracy"],
        ] + [s["state_rmse"][st] for st in result.states]
        rows.append(["" if v is None else v for v in row])
    return head, rows


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


def write_sweep_outputs(
    result: SweepResult, out: str | Path, *, figures: bool = True, extra: Mapping | None = None
) -> list[Path]:
    """Write ``results.json``, ``results.csv`` and the figures into ``out``.

    Figures: ``sweep_<case>.png`` (detection probability with Wilson intervals and median
    delay against magnitude, every method on the same axes) for each fault case, and
    ``confusion_<method>.png`` (the confusion counts summed over the method's cells).

    Args:
        result: the :class:`SweepResult`.
        out: output directory (created).
        figures: also write the figures.
        extra: extra top-level entries for ``results.json``.

    Returns:
        The written paths.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    doc = result.to_json()
    if extra:
        doc.update(extra)
    written = [out / "results.json", out / "results.csv"]
    written[0].write_text(json.dumps(doc, indent=2) + "\n")
    head, rows = _csv_rows(result)
    with written[1].open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        w.writerows(rows)
    if not figures:
        return written
    from uimm_jax import plotting

    for case in result.spec.cases:
        cells = [s for s in result.summaries if s["case"] == case.name]
        fig = plotting.plot_sweep(
            cells,
            title=f"{result.scenario}: case {case.name!r}, {result.spec.runs} runs per cell "
            "(95 % Wilson intervals)",
        )
        written.append(plotting.save_figure(fig, out / f"sweep_{_safe(case.name)}.png"))
    for method in result.spec.methods:
        ss = [s for s in result.summaries if s["method"] == method]
        mat = np.sum([s["confusion"]["matrix"] for s in ss], axis=0)
        conf = ss[0]["confusion"]
        fig = plotting.plot_confusion(
            mat,
            conf["rows"],
            conf["columns"],
            title=f"{method.upper()}: first new declaration per event ({len(ss)} cells)",
        )
        written.append(plotting.save_figure(fig, out / f"confusion_{method}.png"))
    return written
