"""Training batches and the tuning loss: the exact hard diagnoser plus a smooth surrogate.

:func:`make_batch` builds a batch of simulated runs (the truth plans of
:func:`uimm_jax.studies.truth.build_truth_plan`, the noise keys of
:func:`uimm_jax.engine.truth.run_keys`); :func:`loss_and_parts` scans the truth sample
(:func:`uimm_jax.engine.scan.truth_sample`), the diagnoser step and the loss
accumulators over it (see :mod:`uimm_jax.studies.tune` for the losses and the
checkpointed time loop).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine.metrics import new_declarations
from uimm_jax.engine.scan import scan_chunked, truth_scan
from uimm_jax.engine.truth import NEVER, TruthPlan, run_keys
from uimm_jax.engine.uimm import DiagParams, DiagState
from uimm_jax.studies.run import setup_scenario
from uimm_jax.studies.truth import build_truth_plan
from uimm_jax.studies.tune_params import (
    Constrained,
    LossWeights,
    TunableParams,
    TuneConfig,
    constrain,
    diag_params,
)

__all__ = [
    "LossParts",
    "Observed",
    "Problem",
    "RunCase",
    "TrainingBatch",
    "loss_and_parts",
    "make_batch",
    "make_loss_fn",
    "precompute_truth",
    "scenario_case",
    "trace_surrogate",
]

_H_MAX = 1.0 - 1e-12  # hazards are clipped below 1 so that log1p(-h) stays finite


class Observed(NamedTuple):
    """Precomputed truth of a batch (time-major).

    Attributes:
        u: ``(N, p, B)`` inputs.
        y: ``(N, m, B)`` measurements.
        code: ``(N, B)`` int32 true fault-set codes.
    """

    u: jax.Array
    y: jax.Array
    code: jax.Array


class RunCase(NamedTuple):
    """The truth of one kind of run: fault events ``(fault, time_s, magnitude)``.

    Attributes:
        name: label.
        events: tuple of ``(fault, time, magnitude)``; empty for a fault-free run.
    """

    name: str
    events: tuple[tuple[str, float, float], ...]


class TrainingBatch(NamedTuple):
    """A batch of simulated runs (pytree; the runs axis is ``B``).

    Attributes:
        plan: batched :class:`~uimm_jax.engine.truth.TruthPlan` (phases last).
        keys: ``(B, 2)`` raw uint32 noise keys (common random numbers).
        onset: ``(B, F)`` int32 onset step of each fault (``INT32_MAX``: no event).
        init: initial :class:`~uimm_jax.engine.uimm.DiagState` of the batch.
        base: the scenario's :class:`~uimm_jax.engine.uimm.DiagParams` (Q, R, starting values).
        signal: the input signal.
        data: optional precomputed truth (:func:`precompute_truth`); when present the
            loss reads it instead of simulating the truth inside the loop.
    """

    plan: TruthPlan
    keys: jax.Array
    onset: jax.Array
    init: DiagState
    base: DiagParams
    signal: Any
    data: Observed | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """Static description of a tuning problem (hashed by identity).

    Attributes:
        diagnoser: the engine's :class:`~uimm_jax.engine.uimm.Diagnoser`.
        num_steps: samples per run.
        dt: sample time, s.
        input_dim: ``p``.
        case_names: name of each run's case.
        seeds: the seed the batch keys were split from.
        scenario: the scenario the batch was built from.
    """

    diagnoser: Any
    num_steps: int
    dt: float
    input_dim: int
    case_names: tuple[str, ...]
    seeds: int
    scenario: Any

    @property
    def num_models(self) -> int:
        """``M``."""
        return self.diagnoser.num_models


def scenario_case(scenario, time_scale: float = 1.0) -> RunCase:
    """A scenario's own events as a :class:`RunCase` (times multiplied by ``time_scale``)."""
    return RunCase(
        scenario.name,
        tuple((e.fault, float(e.time) * time_scale, float(e.magnitude)) for e in scenario.events),
    )


def make_batch(
    scenario,
    cases: Sequence[RunCase],
    runs_per_case: int | Sequence[int],
    seed: int,
    *,
    duration: float | None = None,
    dtype=None,
) -> tuple[Problem, TrainingBatch]:
    """Build a batch of runs of ``scenario`` (its plant, noise, faults and filter).

    Args:
        scenario: the :class:`~uimm_jax.scenario.spec.Scenario` (UIMM or IMM).
        cases: the truths to simulate (e.g. the scenario's own events and a fault-free run).
        runs_per_case: runs of each case (an int for all, or one per case).
        seed: root seed of the noise keys (:func:`uimm_jax.engine.truth.run_keys`).
        duration: run length in s (default: the scenario's).
        dtype: float dtype (default: JAX's default float).

    Returns:
        ``(problem, batch)``.
    """
    dtype = dtype or jnp.asarray(0.0).dtype
    if scenario.filter.method != "uimm":
        hint = (
            "; its settings are the fixed-size UIMM's too (same bank layout): tune a copy "
            'with [filter] method = "uimm" and set the method back in the result'
            if scenario.filter.method == "uimm-est"
            else ""
        )
        if hint and scenario.filter.est is not None:
            hint += " (drop [filter.est] from the copy, and keep it for the result)"
        raise ValueError(
            f"tuning supports method 'uimm' (the scenario's is {scenario.filter.method!r}){hint}"
        )
    setup = setup_scenario(scenario, dtype=dtype)
    diag = setup.diagnoser
    table = setup.table
    names = list(table.names)
    F = len(names)
    dt = float(scenario.dt)
    dur = float(scenario.duration if duration is None else duration)
    N = int(round(dur / dt))
    if isinstance(runs_per_case, int):
        runs_per_case = [runs_per_case] * len(cases)
    K = max(2, 1 + max((len(c.events) for c in cases), default=0))
    onsets, mags, labels = [], [], []
    for case, nr in zip(cases, runs_per_case, strict=True):
        on = np.full(F, -1, np.int64)
        mag = np.ones(F)
        for fault, t, a in case.events:
            if fault not in names:
                raise ValueError(f"case {case.name!r}: unknown fault {fault!r}")
            j = names.index(fault)
            k = int(round(t / dt))
            if not 0 <= k < N:
                raise ValueError(f"case {case.name!r}: event at {t} s is outside the run")
            if on[j] >= 0:
                raise ValueError(f"case {case.name!r}: fault {fault!r} occurs twice")
            on[j], mag[j] = k, a
        onsets += [on] * nr
        mags += [mag] * nr
        labels += [case.name] * nr
    B = len(labels)
    if B == 0:
        raise ValueError("make_batch: no runs")
    onsets = np.array(onsets)
    plan = build_truth_plan(
        scenario,
        diag.dyn,
        table,
        onsets,
        np.array(mags),
        dtype=dtype,
        num_phases=K,
        hint="the cases' magnitudes and the fault values",
    )
    flt = scenario.filter
    init = diag.init(
        np.asarray(flt.initial_mean),
        np.asarray(flt.initial_cov),
        setup.initial_mode_probs,
        (B,),
        dtype,
    )
    batch = TrainingBatch(
        plan=plan,
        keys=jnp.asarray(run_keys(seed, B)[0]),
        onset=jnp.asarray(np.where(onsets >= 0, onsets, NEVER).astype(np.int32)),
        init=init,
        base=setup.params,
        signal=setup.signal,
    )
    problem = Problem(diag, N, dt, scenario.plant.input_dim, tuple(labels), int(seed), scenario)
    return problem, batch


class LossParts(NamedTuple):
    """Loss terms averaged over the runs, and hard outcomes of the forward pass.

    Attributes:
        total: the weighted loss.
        ce: mean cross-entropy per sample (nats).
        delay: mean over runs of the summed surrogate delays (s).
        false: mean over runs of the cumulative false-declaration hazard.
        decl_step: ``(B, F)`` int32 hard declaration step of each fault (-1: never).
    """

    total: jax.Array
    ce: jax.Array
    delay: jax.Array
    false: jax.Array
    decl_step: jax.Array


class _Acc(NamedTuple):
    ce_sum: jax.Array  # (B,)
    ce_count: jax.Array  # (B,)
    run: jax.Array  # (F, B) soft run length (fault axis first, as the engine's sets)
    log_nofalse: jax.Array  # (F, B) sum of log(1 - h) while absent
    log_surv: jax.Array  # (F, B) log survival since onset (undeclared)
    delay: jax.Array  # (F, B) sum of survivals (steps)
    decl_step: jax.Array  # (F, B) int32


class _Carry(NamedTuple):
    x: jax.Array
    diag: DiagState
    acc: _Acc


def _lse_excluding(log_mu: jax.Array, j: int) -> jax.Array:
    """``logsumexp`` of ``log_mu[i]`` over models ``i != j`` (finite when model 0 is)."""
    M = log_mu.shape[0]
    others = [log_mu[i] for i in range(M) if i != j]
    mx = others[0]
    for o in others[1:]:
        mx = jnp.maximum(mx, o)
    mx = jax.lax.stop_gradient(jnp.where(jnp.isfinite(mx), mx, 0.0))
    return jnp.log(sum(jnp.exp(o - mx) for o in others)) + mx


def _step(problem: Problem, config: TuneConfig, c: Constrained, params, carry, k, u, y, code):
    """One step of the hard diagnoser, the decision surrogate and the loss accumulators."""
    diag = problem.diagnoser
    F = diag.num_faults
    prev = carry.diag
    st, info = diag.step(prev, params, u, y, with_cov=False)
    log_mu = info.step.log_mode_probs  # (M, B) posterior before the decision
    dtype = log_mu.dtype
    acc = carry.acc
    declared0 = prev.declared  # (F, B): the bank this step used
    declared1 = st.declared
    present = ((code[None] >> jnp.arange(F)[:, None]) & 1).astype(bool)  # (F, B)
    # --- cross-entropy against the bank slot of the true fault set --------------------
    extra = present & ~declared0
    n_extra = jnp.sum(extra, axis=0)
    valid = jnp.all(~declared0 | present, axis=0) & (n_extra <= 1)
    true_idx = jnp.where(n_extra == 0, 0, 1 + jnp.argmax(extra, axis=0))
    onehot = true_idx[None] == jnp.arange(log_mu.shape[0])[:, None]
    lm_true = jnp.sum(jnp.where(onehot, log_mu, 0.0), axis=0)
    lm_true = jnp.where(valid, lm_true, 0.0)
    ce_sum = acc.ce_sum - lm_true
    ce_count = acc.ce_count + valid.astype(dtype)
    # --- decision surrogate (UIMM: model j + 1 is "D + fault j") ----------------------
    if not config.couple:
        log_mu = jax.lax.stop_gradient(log_mu)
    logit_thr = jnp.log(c.threshold) - jnp.log1p(-c.threshold)
    qs = []
    for j in range(F):
        act = ~declared0[j]
        lm_j = log_mu[j + 1]
        ok = act & jnp.isfinite(lm_j)
        lm_j = jnp.where(ok, lm_j, 0.0)  # double where: no inf in the differentiated path
        d = (lm_j - _lse_excluding(log_mu, j + 1) - logit_thr) / config.temperature
        d = jnp.where(ok, d, 0.0)
        qs.append(jnp.where(ok, jax.nn.sigmoid(d), 0.0))
    q = jnp.stack(qs)  # (F, B)
    gate = jax.nn.sigmoid((jnp.log1p(acc.run) - c.log_hold_gate) / config.hold_temperature)
    h = jnp.minimum(q * gate, _H_MAX)
    log1m_h = jnp.log1p(-h)
    run = q * (acc.run + 1.0)
    log_nofalse = acc.log_nofalse + jnp.where(present, 0.0, log1m_h)
    window = present & ~declared1
    log_surv = acc.log_surv + jnp.where(window, log1m_h, 0.0)
    delay = acc.delay + jnp.where(window, jnp.exp(log_surv), 0.0)
    decl_step = new_declarations(acc.decl_step, declared0, declared1, k.astype(jnp.int32))
    acc = _Acc(ce_sum, ce_count, run, log_nofalse, log_surv, delay, decl_step)
    # Per-step trace (trace_surrogate only; the loss path drops it): runs first.
    return _Carry(carry.x, st, acc), (log_mu.T, h.T, declared1.T, code)


def _initial_carry(problem: Problem, batch: TrainingBatch) -> _Carry:
    B = batch.keys.shape[0]
    F = problem.diagnoser.num_faults
    n = batch.init.imm.mean.shape[0]
    dtype = batch.init.imm.mean.dtype
    z = jnp.zeros((F, B), dtype)
    acc = _Acc(
        jnp.zeros((B,), dtype),
        jnp.zeros((B,), dtype),
        z,
        z,
        z,
        z,
        jnp.full((F, B), -1, jnp.int32),
    )
    return _Carry(jnp.zeros((n, B), dtype), batch.init, acc)


def _segment_length(N: int, config: TuneConfig) -> int:
    """Checkpoint segment: ``config.segment``, else ``ceil(sqrt(N) / 4)``.

    Memory is ``N / L`` carries plus one segment's residuals (``L`` steps, about four
    times a carry each): ``O(sqrt(N))`` either way.  A quarter of ``sqrt(N)`` keeps the
    residuals of a segment in cache: at 1e6 samples (paper simulation 1) the gradient
    measured 3.23x the forward pass with segments of 1000 samples, 2.74x with 250 and
    2.79x with 100.
    """
    if config.segment is not None:
        return int(min(config.segment, N))
    return max(1, int(math.ceil(math.sqrt(N) / 4)))


def _loop_params(c: Constrained, params, carry: _Carry):
    """The differentiated parameters broadcast to the shapes they meet in the step.

    ``Q``, ``R`` ``(n, n, M, *runs)``, the log transition ``(M, M, *runs)``, the threshold
    ``(*runs,)`` and the persistence gate ``(F, *runs)``, broadcast once, before the time
    loop: the forward pass computes the same numbers, and the reverse sweep adds each
    step's cotangent into a carry of the same shape, where with the small shapes it
    reduced it over the models and runs every step (XLA fused those reductions with
    copies of the cotangents' arithmetic).  Measured (paper simulation 1, 1e5 samples,
    interleaved): the gradient 1.78 -> 1.69 µs per step, the forward pass unchanged
    (``benchmarks/README.md``, the gradient section).
    """
    bshape = carry.diag.imm.cov.shape[2:]  # (M, *runs)
    runs = bshape[1:]
    F = carry.acc.run.shape[0]

    def bank(a):  # (r, c) -> (r, c, M, *runs)
        a = jnp.asarray(a)
        return jnp.broadcast_to(a.reshape(a.shape[:2] + (1,) * len(bshape)), a.shape[:2] + bshape)

    imm = params.imm
    lt = imm.log_transition
    lt = jnp.broadcast_to(lt.reshape(lt.shape[:2] + (1,) * len(runs)), lt.shape[:2] + runs)
    imm = imm._replace(Q=bank(imm.Q), R=bank(imm.R), log_transition=lt)
    c = c._replace(
        threshold=jnp.broadcast_to(c.threshold, runs),
        log_hold_gate=jnp.broadcast_to(c.log_hold_gate, (F,) + runs),
    )
    return c, params._replace(imm=imm)


def _run(problem: Problem, config: TuneConfig, c: Constrained, params, batch, carry):
    """Scan the fused step over all samples (nested, checkpointed scan).

    With the truth in the loop, each segment first simulates its ``L`` samples into a
    segment-sized buffer (:func:`uimm_jax.engine.scan.truth_scan`, the noise drawn at once),
    then scans the diagnoser step over the buffer; the checkpoint covers both, so memory
    stays ``O(sqrt(N))``.  Measured against one scan that simulated and filtered each
    sample in turn (paper simulation 1, 1e6 samples, segments of 250, interleaved in one
    process): the forward pass 0.64 against 0.83 µs per step, the gradient 2.16 against
    2.57, the same loss and gradient to the last bit (``benchmarks/README.md``, the
    gradient section).
    """
    N = problem.num_steps
    L = _segment_length(N, config)
    S, rem = divmod(N, L)
    data = batch.data
    p = problem.input_dim
    c, params = _loop_params(c, params, carry)

    def body(cc, xs):
        k, u, y, code = xs
        if data is None:  # the truth's scalar input, applied to every channel
            u = jnp.full((p,) + cc.x.shape[1:], u, cc.x.dtype)
        return _step(problem, config, c, params, cc, k, u, y, code)[0], None

    def segment(cr, xs):
        if data is None:  # the segment's truth, simulated into a buffer
            dyn, dt = problem.diagnoser.dyn, problem.dt
            plan, signal, keys = batch.plan, batch.signal, batch.keys
            x_end, (u, _, y, code) = truth_scan(dyn, dt, p, plan, signal, keys, cr.x, xs)
            cr, _ = jax.lax.scan(body, cr, (xs, u, y, code))
            return cr._replace(x=x_end)
        cr, _ = jax.lax.scan(body, cr, xs)
        return cr

    seg = jax.checkpoint(segment) if config.checkpoint else segment
    ks = jnp.arange(N, dtype=jnp.int32)
    xs = ks if data is None else (ks, data.u, data.y, data.code)
    if S == 1:
        carry = seg(carry, jax.tree.map(lambda a: a[:L], xs))
    else:
        head = jax.tree.map(lambda a: a[: S * L].reshape((S, L) + a.shape[1:]), xs)
        carry, _ = jax.lax.scan(lambda cr, xx: (seg(cr, xx), None), carry, head)
    if rem:
        carry = seg(carry, jax.tree.map(lambda a: a[S * L :], xs))
    return carry


def precompute_truth(problem: Problem, batch: TrainingBatch, *, chunk: int = 50_000):
    """Simulate the batch's truth once and store it in ``batch.data``.

    Training then reads the measurements instead of simulating them inside the loss (the
    truth does not depend on the tuned parameters): faster iterations and a smaller
    compiled gradient, at ``N * B * (p + m + 1)`` stored numbers.

    Returns:
        The batch with ``data`` set.
    """
    n = batch.init.imm.mean.shape[0]
    B = batch.keys.shape[0]
    dtype = batch.init.imm.mean.dtype
    dyn, dt, p = problem.diagnoser.dyn, problem.dt, problem.input_dim
    fn = jax.jit(lambda b, x, ks: truth_scan(dyn, dt, p, b.plan, b.signal, b.keys, x, ks))

    def chunk_fn(x, k0, ks):  # the chunk's truth (engine.scan), inputs on every channel
        x, (u, _, y, code) = fn(batch, x, ks)
        return x, (jnp.broadcast_to(u[:, None, None], (u.shape[0], p, B)), y, code)

    x0 = jnp.zeros((n, B), dtype)
    _, (u, y, code) = scan_chunked(chunk_fn, x0, problem.num_steps, chunk=chunk)
    return batch._replace(data=Observed(jnp.asarray(u), jnp.asarray(y), jnp.asarray(code)))


def loss_and_parts(
    raw: TunableParams,
    problem: Problem,
    batch: TrainingBatch,
    config: TuneConfig,
    weights: jax.Array | LossWeights | None = None,
) -> tuple[jax.Array, LossParts]:
    """The tuning loss of ``raw`` on a batch of runs (not jitted; see :func:`make_loss_fn`).

    Args:
        raw: the :class:`TunableParams`.
        problem: the :class:`Problem`.
        batch: the :class:`TrainingBatch`.
        config: the :class:`TuneConfig`.
        weights: ``(3,)`` weights ``(ce, delay, false)`` (a traced argument, so that a
            schedule does not recompile); default ``config.weights``.

    Returns:
        ``(loss, parts)`` with ``parts`` a :class:`LossParts`.
    """
    M = problem.num_models
    c = constrain(raw, M, config)
    params = diag_params(c, batch.base)
    carry = _run(problem, config, c, params, batch, _initial_carry(problem, batch))
    a = carry.acc
    dtype = a.ce_sum.dtype
    ce = jnp.mean(a.ce_sum / jnp.maximum(a.ce_count, 1.0))
    delay = jnp.mean(jnp.sum(a.delay, axis=0)) * problem.dt
    false = jnp.mean(jnp.sum(-a.log_nofalse, axis=0))
    w = jnp.asarray(config.weights if weights is None else weights, dtype)
    total = (w[0] * ce + w[1] * delay + w[2] * false).astype(dtype)
    return total, LossParts(total, ce, delay, false, a.decl_step.T)


def trace_surrogate(raw: TunableParams, problem: Problem, batch: TrainingBatch, config):
    """Per-step trace of the forward pass (for inspection and plots; memory ``O(N)``).

    Returns:
        dict of NumPy arrays: ``mode_probs`` ``(N, B, M)``, ``hazard`` ``(N, B, F)`` (the
        soft declaration hazard ``h``), ``declared`` ``(N, B, F)`` (hard, after the step)
        and ``truth`` ``(N, B)`` fault-set codes.
    """
    M = problem.num_models
    data = batch.data if batch.data is not None else precompute_truth(problem, batch).data

    @jax.jit
    def run(raw, batch, data):
        c = constrain(raw, M, config)
        params = diag_params(c, batch.base)

        def body(cc, xs):
            k, u, y, code = xs
            return _step(problem, config, c, params, cc, k, u, y, code)

        ks = jnp.arange(problem.num_steps, dtype=jnp.int32)
        return jax.lax.scan(body, _initial_carry(problem, batch), (ks, *data))[1]

    log_mu, h, declared, code = jax.tree.map(np.asarray, run(raw, batch, data))
    return {"mode_probs": np.exp(log_mu), "hazard": h, "declared": declared, "truth": code}


@functools.lru_cache(maxsize=16)
def make_loss_fn(problem: Problem, config: TuneConfig) -> tuple[Callable, Callable]:
    """Jitted ``loss(raw, batch, weights=None) -> (loss, parts)`` and its value and gradient.

    Cached per ``(problem, config)``: calling it again (e.g. from :func:`fit`) reuses the
    compiled functions; ``weights`` is traced (default ``config.weights``).

    Returns:
        ``(loss_fn, value_and_grad_fn)``; the gradient is with respect to ``raw``.
    """

    def f(raw, batch, weights):
        return loss_and_parts(raw, problem, batch, config, weights)

    f_jit = jax.jit(f)
    vg_jit = jax.jit(jax.value_and_grad(f, has_aux=True))

    def _w(weights):
        return jnp.asarray(config.weights if weights is None else weights, jnp.float64)

    def loss_fn(raw, batch, weights=None):
        return f_jit(raw, batch, _w(weights))

    def value_and_grad_fn(raw, batch, weights=None):
        return vg_jit(raw, batch, _w(weights))

    return loss_fn, value_and_grad_fn
