"""One batch of a sweep: its inputs, and its scan over every step, sharded over devices.

:func:`batch_inputs` builds a batch's truth plan, noise keys and initial carry (the engine's
layout: small axes, models, runs); :func:`run_batch` drives the fused simulate -> diagnose
chunk over the whole run (:func:`uimm_jax.engine.scan.simulate_diagnose`), on one device
or ``shard_map``-ed over a ``Mesh`` whose ``"runs"`` axis splits the run axis of every
batched leaf (every process of a ``jax.distributed`` run holding the same host values).
Used by :func:`uimm_jax.studies.sweep.run_sweep` and the benchmarks.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine.metrics import RunMetrics, init_est_metrics, init_metrics
from uimm_jax.engine.scan import SimCarry, scan_chunked, simulate_diagnose
from uimm_jax.engine.truth import TruthPlan
from uimm_jax.engine.uimm_est import UIMMEstDiagnoser
from uimm_jax.studies.run import RunSetup
from uimm_jax.studies.truth import build_truth_plan

__all__ = ["CHUNK_COMPILER_OPTIONS", "batch_inputs", "run_batch"]


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
    growth=None,
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
        growth: optional ``(B, F)`` growth code of each fault's ramp.
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
        growth=growth,
        where="[sweep]: ",
        hint="the magnitudes and the fault values",
    )
    n = scenario.plant.state_dim
    carry = SimCarry(
        x=jnp.zeros((n, B), dtype),
        diag=_broadcast_state(setup.init_state, B),
        metrics=init_metrics(B, scenario.num_faults, n, dtype, scenario.plant.output_dim),
        est=(
            init_est_metrics(B, scenario.num_faults, dtype)
            if isinstance(setup.diagnoser, UIMMEstDiagnoser)
            else None
        ),
    )
    return plan, jnp.asarray(keys), carry


CHUNK_COMPILER_OPTIONS = {"xla_cpu_prefer_vector_width": 512}
"""XLA options of the compiled sweep chunk (:func:`run_batch`), one device or sharded.

``xla_cpu_prefer_vector_width=512`` lets LLVM use 512-bit vectors (8 doubles) where the
CPU has them (AVX-512); elsewhere the widest the CPU has is used, as by default (256).
Measured on the 2-core AVX-512 development VM (benchmarks/README.md, "Monte Carlo
throughput", session 8): the fused chunk at 64 runs takes 6-7 % less CPU time per
run-step, with the same bits (every metric and filter state, batches of 16, 24, 48 and
64 runs).  A per-computation option: nothing else in the process is compiled with it."""

_jit_chunk = jax.jit(
    simulate_diagnose, static_argnums=(0, 1, 2), compiler_options=CHUNK_COMPILER_OPTIONS
)


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
        cache_end=None if plan.cache_end is None else t(plan.cache_end, 1),
    )
    return carry_spec, plan_spec, t(keys, 1)


@functools.lru_cache(maxsize=32)
def _sharded_chunk(diag, dt, p, mesh, carry_spec, plan_spec, keys_spec, options=None):
    """A jitted, shard_mapped chunk function (cached: built and compiled once).

    ``options``: XLA compile options as a tuple of pairs (default:
    :data:`CHUNK_COMPILER_OPTIONS`; ``()`` for XLA's defaults, as the benchmarks compare).
    """
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
    opts = CHUNK_COMPILER_OPTIONS if options is None else dict(options)
    return jax.jit(smap, compiler_options=opts or None)


def _place(tree, specs, mesh):
    """Global arrays split over ``mesh`` (every process holds the same host values)."""
    from jax.sharding import NamedSharding

    if jax.process_count() == 1:
        return jax.tree.map(lambda a, s: jax.device_put(a, NamedSharding(mesh, s)), tree, specs)

    def put(a, s):
        host = np.asarray(a)
        return jax.make_array_from_callback(host.shape, NamedSharding(mesh, s), host.__getitem__)

    return jax.tree.map(put, tree, specs)


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
