"""Gradient tuning of the diagnoser's transition matrix and decision rule with optax.

The paper picks its transition matrix and threshold "based on historical experience"
and they do not diagnose at 10 kHz (design.md section 3).  This module tunes them by
gradient descent on a loss computed over a batch of simulated runs (common random
numbers: the same truth noise at every iteration), with the exact engine in the loop.

**Parameters** (:class:`TunableParams`, an unconstrained pytree; what optax sees):

* ``transition_logits``: rows of the transition matrix through a log-softmax.  The
  ``structure`` of :class:`TuneConfig` is ``"full"`` (an ``M x M`` logit matrix),
  ``"tied"`` (faults exchangeable: row 0 has a stay and one shared "fault j appears"
  logit; every fault row has the same "back to D", stay and "other fault" logits -- 5
  numbers whatever ``F``, so faults absent from the training runs get the same treatment
  as the trained ones), ``"row_stay"`` (one stay logit per row, the rest of the row
  shared equally) or ``"stay"`` (one stay logit for every row, the scenario file's
  ``stay``).  With ``irreversible=True`` the fault models' rows are absorbing
  (probability 1 of staying): "faults are irreversible" as a structural zero pattern.
* ``threshold_logit``: ``threshold = sigmoid(threshold_logit)`` (``mu_f`` of eq. 29).
* ``log_hold``: the persistence as ``hold = 0.5 + exp(log_hold)`` (a real number during
  training; the hard rule uses ``max(1, round(hold))``).
* ``log_q_scale``, ``log_r_scale``: optional multiplicative scales of the filter's ``Q``
  and ``R`` (not written to scenario files: a scenario's ``[noise]`` is also the truth's).

Parameters not tuned (:class:`TuneConfig` flags) pass through ``lax.stop_gradient``.

**Relaxation of the hard rule (straight-through).**  The forward pass of the loss *is*
the exact hard diagnoser: :meth:`uimm_jax.engine.uimm.Diagnoser.step`, with the hard threshold
crossing, the persistence counter, the masked parameter replacement and the ``lax.cond``
re-discretisation, run with the current parameters.  The declaration events are therefore
the ones the evaluation sees; their effect on the bank (which model set the filters use
after a declaration) is not differentiated -- a straight-through treatment of the
replacement.  What is differentiated is everything continuous: the IMM mixing and the
Kalman filters (transition matrix, noise scales) and a smooth *decision surrogate* that
runs beside the hard rule on the same mode probabilities:

* decision statistic of fault ``j`` (model ``j+1``), in logit units:
  ``d_j = logit(mu_j) - logit(threshold)``, with ``logit(mu_j) = log mu_j -
  logsumexp_{i != j} log mu_i`` (computed in log space; ``mu_j >= threshold`` iff
  ``d_j >= 0``);
* soft qualification ``q_j = sigmoid(d_j / temperature)`` (0 for declared faults);
* soft run length ``r_j[k] = q_j[k] (r_j[k-1] + 1)`` (the hard counter when ``q`` is 0/1;
  per model, which equals the engine's single counter when ``threshold >= 0.5``);
* soft declaration hazard ``h_j[k] = q_j[k] sigmoid((log(r_j[k-1] + 1) - log(hold - 0.5))
  / hold_temperature)`` (the hard rule declares when ``r[k-1] + 1 >= hold``).

**Losses** (per run, then averaged over the batch; :class:`LossParts`):

* cross-entropy ``-mean_k log mu_true[k]``, the true model being the bank slot of the true
  fault set relative to the declared set ``D`` (model 0 when the truth is ``D``, model
  ``j+1`` when it is ``D + f_j``; steps where the truth is not in the bank are skipped);
* detection delay: for each fault event, the expected first-passage time under the soft
  hazard, ``dt * sum_{k0 <= k < k_d} prod_{i=k0..k} (1 - h_j[i])`` where ``k_d`` is the
  hard declaration step (the end of the run if never declared): the hazard is forced to
  one at the hard declaration, so the surrogate is at most the hard delay;
* false declarations: for each fault, minus the log-probability of no declaration while
  it is absent from the truth under the soft hazard, ``-sum_k log(1 - h_j[k])`` over
  those steps (the cumulative hazard; summed over faults).  Unlike ``1 - prod(1 - h)``
  its gradient does not vanish once one step's hazard saturates.

``loss = w_ce * ce + w_delay * delay_s + w_false * false`` (default weights 100, 10, 10).

**Gradient routing.**  By default (``TuneConfig.couple=False``) the decision terms see the
mode probabilities through ``lax.stop_gradient``: the filter parameters (transition,
noise scales) follow the cross-entropy alone and the decision parameters (threshold,
hold) the delay and false-declaration terms.  Each block's gradient is the exact gradient
of its own objective (checked against finite differences in ``tests/test_tuning.py``).
With ``couple=True`` the whole loss is differentiated with respect to every parameter.
Measured on paper simulation 1 from the paper's settings, the coupled gradient makes the
chain *less* sticky (the cheapest way to shrink the false-declaration hazard) until
nothing is ever declared, a flat region of the delay surrogate; the decoupled one makes
the chain sticky (cross-entropy) while raising the threshold and the persistence.

**Long runs.**  The time loop is a nested ``lax.scan``: the outer scan runs segments of
``segment`` steps (``sqrt(N)`` by default), each segment a ``jax.checkpoint``-ed inner scan
of the fused truth + diagnoser + surrogate step.  Reverse mode stores one carry per
segment and recomputes one segment at a time: memory ``O(sqrt(N))`` (see
``benchmarks/bench_gradient.py`` and ``docs/tuning.md`` for measured figures).  The truth
is simulated inside the loop from ``fold_in(key, k)`` (nothing per step is stored).

**Evaluation** always uses the exact hard rule: :func:`hard_metrics` reads the hard
declarations of the training forward pass, and :func:`evaluate` / :func:`before_after`
(used by the CLI, :mod:`uimm_jax.tune_cli`) run :func:`uimm_jax.montecarlo.run_sweep` on
held-out seeds.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine.uimm import DiagParams, DiagState
from uimm_jax.simulate import TruthPlan, input_value, noise_factor, truth_step

__all__ = [
    "STRUCTURES",
    "Constrained",
    "FitResult",
    "LossParts",
    "LossWeights",
    "Observed",
    "Problem",
    "RunCase",
    "TrainingBatch",
    "TunableParams",
    "TuneConfig",
    "before_after",
    "before_after_table",
    "constrain",
    "diag_params",
    "evaluate",
    "fit",
    "hard_hold",
    "hard_metrics",
    "init_params",
    "loss_and_parts",
    "make_batch",
    "make_loss_fn",
    "precompute_truth",
    "rescale_scenario",
    "run_keys",
    "scenario_case",
    "settings_from_params",
    "trace_surrogate",
    "tuned_scenario",
]

STRUCTURES = ("full", "tied", "row_stay", "stay")
"""Transition-matrix parameterisations (see the module doc)."""

_H_MAX = 1.0 - 1e-12  # hazards are clipped below 1 so that log1p(-h) stays finite
_NEVER = np.iinfo(np.int32).max


# --------------------------------------------------------------------------------------
# Configuration and parameters
# --------------------------------------------------------------------------------------


class LossWeights(NamedTuple):
    """Weights of the loss terms.

    Attributes:
        ce: cross-entropy of the mode probabilities (nats per sample).
        delay: expected detection delay (per second, summed over fault events).
        false: cumulative false-declaration hazard per run (nats).
    """

    ce: float = 100.0
    delay: float = 10.0
    false: float = 10.0


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """Static tuning configuration (hashable; changing it recompiles).

    Attributes:
        structure: transition parameterisation, one of :data:`STRUCTURES`.
        irreversible: make the fault models' rows absorbing (structural zeros: once a
            fault model, always that fault model); their logits then have no effect.
        tune_transition: tune the transition logits.
        tune_threshold: tune the threshold.
        tune_hold: tune the persistence.
        tune_noise: tune the scales of the filter's ``Q`` and ``R``.
        couple: let the gradients of the decision terms (delay, false) reach the filter
            parameters (transition, noise scales) through the mode probabilities.  Off by
            default: the filter parameters then follow the cross-entropy alone and the
            decision parameters (threshold, hold) the decision terms (see the module doc).
        temperature: decision-statistic temperature, logit units.
        hold_temperature: persistence-gate temperature, log-run-length units.
        weights: :class:`LossWeights`.
        segment: checkpoint segment length in steps (``None``: ``ceil(sqrt(N))``).
        checkpoint: checkpoint the segments (off: plain reverse mode, memory ``O(N)``).
    """

    structure: str = "full"
    irreversible: bool = False
    tune_transition: bool = True
    tune_threshold: bool = True
    tune_hold: bool = True
    tune_noise: bool = False
    couple: bool = False
    temperature: float = 0.5
    hold_temperature: float = 0.25
    weights: LossWeights = LossWeights()
    segment: int | None = None
    checkpoint: bool = True

    def __post_init__(self):
        if self.structure not in STRUCTURES:
            raise ValueError(f"structure: expected one of {STRUCTURES}, got {self.structure!r}")
        if not (self.temperature > 0 and self.hold_temperature > 0):
            raise ValueError("temperature and hold_temperature must be > 0")
        if self.segment is not None and self.segment < 1:
            raise ValueError(f"segment: expected >= 1, got {self.segment}")


class TunableParams(NamedTuple):
    """Unconstrained tunable parameters (the pytree optax updates).

    Attributes:
        transition_logits: ``(M, M)`` (``"full"``), ``(5,)`` (``"tied"``: stay of ``D``,
            "fault appears", "back to ``D``", stay of a fault model, "other fault"),
            ``(M,)`` (``"row_stay"``) or ``()`` (``"stay"``).
        threshold_logit: ``()``, ``threshold = sigmoid(threshold_logit)``.
        log_hold: ``()``, ``hold = 0.5 + exp(log_hold)``.
        log_q_scale: ``()``, the filter's ``Q`` is ``exp(log_q_scale) Q``.
        log_r_scale: ``()``, the filter's ``R`` is ``exp(log_r_scale) R``.
    """

    transition_logits: jax.Array
    threshold_logit: jax.Array
    log_hold: jax.Array
    log_q_scale: jax.Array
    log_r_scale: jax.Array


def _logit(p: float) -> float:
    return math.log(p) - math.log1p(-p)


def init_params(transition, threshold: float, hold: int, config: TuneConfig) -> TunableParams:
    """Unconstrained parameters that reproduce given settings (as far as the structure can).

    Args:
        transition: ``(M, M)`` row-stochastic starting matrix.
        threshold: starting threshold in ``(0, 1)``.
        hold: starting persistence (integer >= 1).
        config: the :class:`TuneConfig` (its ``structure``).

    Returns:
        :class:`TunableParams` (float64 NumPy-backed arrays).
    """
    P = np.asarray(transition, np.float64)
    M = P.shape[0]
    thr = float(np.clip(threshold, 1e-12, 1 - 1e-12))
    diag = np.clip(np.diag(P), 1e-300, 1 - 1e-16)
    if config.structure == "full":
        with np.errstate(divide="ignore"):
            logits = np.log(np.maximum(P, 1e-300))
        logits = logits - logits.max(axis=1, keepdims=True)
    elif config.structure == "tied":
        logits = np.log(np.maximum(_tied_projection(P), 1e-300))
        logits = np.array(
            [logits[0, 0], logits[0, 1], logits[1, 0], logits[1, 1], logits[1, 2] if M > 2 else 0.0]
        )
    elif config.structure == "row_stay":
        # stay_i = sigmoid(logit_i) with the rest shared equally.
        logits = np.log(diag) - np.log1p(-diag)
    else:
        s = float(np.mean(diag))
        logits = np.asarray(math.log(s) - math.log1p(-s))
    del M
    return TunableParams(
        jnp.asarray(logits, jnp.float64),
        jnp.asarray(_logit(thr), jnp.float64),
        jnp.asarray(math.log(max(float(hold) - 0.5, 1e-6)), jnp.float64),
        jnp.asarray(0.0, jnp.float64),
        jnp.asarray(0.0, jnp.float64),
    )


def _tied_projection(P: np.ndarray) -> np.ndarray:
    """The exchangeable (``"tied"``) matrix closest in the mean to ``P``: averaged entries."""
    M = P.shape[0]
    off0 = P[0, 1:].mean() if M > 1 else 0.0
    out = np.full((M, M), 0.0)
    out[0, 0] = P[0, 0]
    out[0, 1:] = off0
    if M > 1:
        back = P[1:, 0].mean()
        stay = np.diag(P)[1:].mean()
        cross = (P[1:, 1:].sum() - np.trace(P[1:, 1:])) / max((M - 1) * (M - 2), 1)
        out[1:, 0] = back
        out[1:, 1:] = cross
        out[np.arange(1, M), np.arange(1, M)] = stay
    return out / out.sum(axis=1, keepdims=True)


class Constrained(NamedTuple):
    """Constrained values of :class:`TunableParams`.

    Attributes:
        log_transition: ``(M, M)`` log of the transition matrix (rows normalised).
        threshold: ``()`` in ``(0, 1)``.
        hold: ``()`` real persistence ``> 0.5``.
        log_hold_gate: ``()`` ``log(hold - 0.5)``, the persistence gate's centre.
        q_scale: ``()`` scale of ``Q``.
        r_scale: ``()`` scale of ``R``.
    """

    log_transition: jax.Array
    threshold: jax.Array
    hold: jax.Array
    log_hold_gate: jax.Array
    q_scale: jax.Array
    r_scale: jax.Array


def _log_transition(logits: jax.Array, M: int, config: TuneConfig) -> jax.Array:
    """``(M, M)`` log transition matrix from the structured logits."""
    eye = jnp.eye(M, dtype=bool)
    if config.structure == "full":
        z = logits
        if config.irreversible:
            allowed = jnp.asarray(np.vstack([np.ones((1, M), bool), np.eye(M, dtype=bool)[1:]]))
            # Double where: masked entries are -inf in the value and carry no gradient.
            z = jnp.where(allowed, jnp.where(allowed, z, 0.0), -jnp.inf)
        return jax.nn.log_softmax(z, axis=-1)
    if config.structure == "tied":
        s0, e, b, s1, x = (logits[i] for i in range(5))
        col = jnp.arange(M)[None, :]
        row = jnp.arange(M)[:, None]
        z = jnp.where(
            row == 0,
            jnp.where(col == 0, s0, e),
            jnp.where(col == 0, b, jnp.where(col == row, s1, x)),
        )
        if config.irreversible:
            z = jnp.where((row == 0) | (col == row), z, -jnp.inf)
        return jax.nn.log_softmax(z, axis=-1)
    stay = jnp.broadcast_to(logits, (M,)) if config.structure == "stay" else logits
    log_s = jax.nn.log_sigmoid(stay)  # log stay
    log_o = jax.nn.log_sigmoid(-stay) - math.log(max(M - 1, 1))  # log off-diagonal share
    out = jnp.where(eye, log_s[:, None], log_o[:, None])
    if config.irreversible:
        row = jnp.arange(M)[:, None]
        out = jnp.where(row == 0, out, jnp.where(eye, 0.0, -jnp.inf))
    return out


def constrain(raw: TunableParams, M: int, config: TuneConfig) -> Constrained:
    """Map unconstrained parameters to their constrained values.

    Parameters that ``config`` does not tune are passed through ``lax.stop_gradient``.
    """
    sg = jax.lax.stop_gradient

    def pick(x, on):
        return x if on else sg(x)

    logits = pick(raw.transition_logits, config.tune_transition)
    thr_l = pick(raw.threshold_logit, config.tune_threshold)
    lh = pick(raw.log_hold, config.tune_hold)
    lq = pick(raw.log_q_scale, config.tune_noise)
    lr = pick(raw.log_r_scale, config.tune_noise)
    return Constrained(
        log_transition=_log_transition(logits, M, config),
        threshold=jax.nn.sigmoid(thr_l),
        hold=0.5 + jnp.exp(lh),
        log_hold_gate=lh,
        q_scale=jnp.exp(lq),
        r_scale=jnp.exp(lr),
    )


def hard_hold(hold: jax.Array) -> jax.Array:
    """The integer persistence the hard rule uses: ``max(1, round(hold))`` (int32)."""
    return jnp.maximum(1, jnp.round(jax.lax.stop_gradient(hold))).astype(jnp.int32)


def diag_params(c: Constrained, base: DiagParams) -> DiagParams:
    """The engine's :class:`~uimm_jax.engine.uimm.DiagParams` for constrained values."""
    imm = base.imm._replace(
        log_transition=c.log_transition.astype(base.imm.Q.dtype),
        Q=base.imm.Q * c.q_scale,
        R=base.imm.R * c.r_scale,
    )
    return DiagParams(imm, c.threshold.astype(base.imm.Q.dtype), hard_hold(c.hold))


def settings_from_params(raw: TunableParams, M: int, config: TuneConfig) -> dict[str, Any]:
    """Host values of the filter settings: transition, threshold, hold, noise scales."""
    c = jax.tree.map(np.asarray, constrain(raw, M, config))
    P = np.exp(np.asarray(c.log_transition, np.float64))
    P = P / P.sum(axis=1, keepdims=True)
    return {
        "transition": P,
        "threshold": float(c.threshold),
        "hold_real": float(c.hold),
        "hold": int(max(1, round(float(c.hold)))),
        "q_scale": float(c.q_scale),
        "r_scale": float(c.r_scale),
    }


# --------------------------------------------------------------------------------------
# Training batches
# --------------------------------------------------------------------------------------


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
        plan: batched :class:`~uimm_jax.simulate.TruthPlan` (phases last).
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


def run_keys(seed: int, runs: int) -> np.ndarray:
    """``(runs, 2)`` raw noise keys: ``split(split(PRNGKey(seed), runs)[r])[0]``.

    The same derivation as :func:`uimm_jax.montecarlo.run_keys`, so a training seed and
    an evaluation seed that differ give disjoint noise.
    """
    with jax.default_device(jax.devices("cpu")[0]):
        keys = jax.random.split(jax.random.PRNGKey(int(seed)), int(runs))
        both = np.asarray(jax.vmap(jax.random.split)(keys))
    return both[:, 0]


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
        scenario: the :class:`~uimm_jax.scenarios.Scenario` (UIMM or IMM).
        cases: the truths to simulate (e.g. the scenario's own events and a fault-free run).
        runs_per_case: runs of each case (an int for all, or one per case).
        seed: root seed of the noise keys (:func:`run_keys`).
        duration: run length in s (default: the scenario's).
        dtype: float dtype (default: JAX's default float).

    Returns:
        ``(problem, batch)``.
    """
    from uimm_jax.runner import setup_scenario

    dtype = dtype or jnp.asarray(0.0).dtype
    if scenario.filter.method != "uimm":
        raise ValueError(
            f"tuning supports method 'uimm' (the scenario's is {scenario.filter.method!r})"
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
    thetas, codes, steps, onsets, labels = [], [], [], [], []
    for case, nr in zip(cases, runs_per_case, strict=True):
        present = np.zeros(F, bool)
        mags = np.ones(F)
        th = [table.nominal.copy()]
        cd = [0]
        st = []
        on = np.full(F, _NEVER, np.int64)
        for fault, t, mag in sorted(case.events, key=lambda e: e[1]):
            if fault not in names:
                raise ValueError(f"case {case.name!r}: unknown fault {fault!r}")
            j = names.index(fault)
            k = int(round(t / dt))
            if not 0 <= k < N:
                raise ValueError(f"case {case.name!r}: event at {t} s is outside the run")
            present[j] = True
            mags[j] = mag
            on[j] = k
            th.append(table.theta_numpy(present, mags))
            cd.append(int(np.sum(present * (1 << np.arange(F)))))
            st.append(k)
        while len(th) < K:
            th.append(th[-1])
            cd.append(cd[-1])
            st.append(_NEVER)
        for _ in range(nr):
            thetas.append(np.array(th))
            codes.append(cd)
            steps.append(st)
            onsets.append(on)
            labels.append(case.name)
    B = len(labels)
    if B == 0:
        raise ValueError("make_batch: no runs")
    theta = jnp.asarray(np.moveaxis(np.array(thetas), -1, 0), dtype)  # (P, B, K)
    plan = TruthPlan(
        cache=diag.dyn.prepare(theta),
        event_steps=jnp.asarray(np.array(steps, np.int64).reshape(B, K - 1).astype(np.int32)),
        true_codes=jnp.asarray(np.array(codes, np.int32)),
        Gq=jnp.asarray(noise_factor(scenario.process_noise), dtype),
        Gr=jnp.asarray(noise_factor(scenario.measurement_noise), dtype),
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
        keys=jnp.asarray(run_keys(seed, B)),
        onset=jnp.asarray(np.array(onsets).astype(np.int32)),
        init=init,
        base=setup.params,
        signal=setup.signal,
    )
    problem = Problem(diag, N, dt, scenario.plant.input_dim, tuple(labels), int(seed), scenario)
    return problem, batch


# --------------------------------------------------------------------------------------
# The fused step and the loss
# --------------------------------------------------------------------------------------


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
    run: jax.Array  # (B, F) soft run length
    log_nofalse: jax.Array  # (B, F) sum of log(1 - h) while absent
    log_surv: jax.Array  # (B, F) log survival since onset (undeclared)
    delay: jax.Array  # (B, F) sum of survivals (steps)
    decl_step: jax.Array  # (B, F) int32


class _Carry(NamedTuple):
    x: jax.Array
    diag: DiagState
    acc: _Acc


def _lse_excluding(log_mu: jax.Array, j: int) -> jax.Array:
    """``logsumexp`` of ``log_mu[..., i]`` over ``i != j`` (finite when model 0 is)."""
    M = log_mu.shape[-1]
    others = [log_mu[..., i] for i in range(M) if i != j]
    mx = others[0]
    for o in others[1:]:
        mx = jnp.maximum(mx, o)
    mx = jax.lax.stop_gradient(jnp.where(jnp.isfinite(mx), mx, 0.0))
    return jnp.log(sum(jnp.exp(o - mx) for o in others)) + mx


def _truth(problem: Problem, batch: TrainingBatch, x: jax.Array, k: jax.Array):
    """Input and truth step ``k`` of every run: ``(u, x_next, y, code)``."""
    dtype = x.dtype
    B = x.shape[1]
    t = k.astype(dtype) * problem.dt
    u = jnp.full((problem.input_dim, B), input_value(batch.signal, t), dtype)
    x, y, code = truth_step(problem.diagnoser.dyn, batch.plan, x, k, u, batch.keys)
    return u, x, y, code


def _step(problem: Problem, config: TuneConfig, c: Constrained, params, carry, k, u, y, code):
    """One step of the hard diagnoser, the decision surrogate and the loss accumulators."""
    diag = problem.diagnoser
    F = diag.num_faults
    prev = carry.diag
    st, info = diag.step(prev, params, u, y, with_cov=False)
    log_mu = info.step.log_mode_probs  # (B, M) posterior before the decision
    dtype = log_mu.dtype
    acc = carry.acc
    declared0 = prev.declared  # (B, F): the bank this step used
    declared1 = st.declared
    present = ((code[:, None] >> jnp.arange(F)) & 1).astype(bool)  # (B, F)
    # --- cross-entropy against the bank slot of the true fault set --------------------
    extra = present & ~declared0
    n_extra = jnp.sum(extra, axis=-1)
    valid = jnp.all(~declared0 | present, axis=-1) & (n_extra <= 1)
    true_idx = jnp.where(n_extra == 0, 0, 1 + jnp.argmax(extra, axis=-1))
    onehot = true_idx[:, None] == jnp.arange(log_mu.shape[-1])
    lm_true = jnp.sum(jnp.where(onehot, log_mu, 0.0), axis=-1)
    lm_true = jnp.where(valid, lm_true, 0.0)
    ce_sum = acc.ce_sum - lm_true
    ce_count = acc.ce_count + valid.astype(dtype)
    # --- decision surrogate (UIMM: model j + 1 is "D + fault j") ----------------------
    if not config.couple:
        log_mu = jax.lax.stop_gradient(log_mu)
    logit_thr = jnp.log(c.threshold) - jnp.log1p(-c.threshold)
    qs = []
    for j in range(F):
        act = ~declared0[:, j]
        lm_j = log_mu[:, j + 1]
        ok = act & jnp.isfinite(lm_j)
        lm_j = jnp.where(ok, lm_j, 0.0)  # double where: no inf in the differentiated path
        d = (lm_j - _lse_excluding(log_mu, j + 1) - logit_thr) / config.temperature
        d = jnp.where(ok, d, 0.0)
        qs.append(jnp.where(ok, jax.nn.sigmoid(d), 0.0))
    q = jnp.stack(qs, axis=-1)  # (B, F)
    gate = jax.nn.sigmoid((jnp.log1p(acc.run) - c.log_hold_gate) / config.hold_temperature)
    h = jnp.minimum(q * gate, _H_MAX)
    log1m_h = jnp.log1p(-h)
    run = q * (acc.run + 1.0)
    log_nofalse = acc.log_nofalse + jnp.where(present, 0.0, log1m_h)
    window = present & ~declared1
    log_surv = acc.log_surv + jnp.where(window, log1m_h, 0.0)
    delay = acc.delay + jnp.where(window, jnp.exp(log_surv), 0.0)
    newly = declared1 & ~declared0
    decl_step = jnp.where(newly, k.astype(jnp.int32), acc.decl_step)
    acc = _Acc(ce_sum, ce_count, run, log_nofalse, log_surv, delay, decl_step)
    return _Carry(carry.x, st, acc), (log_mu, h, declared1, code)


def _initial_carry(problem: Problem, batch: TrainingBatch) -> _Carry:
    B = batch.keys.shape[0]
    F = problem.diagnoser.num_faults
    n = batch.init.imm.mean.shape[0]
    dtype = batch.init.imm.mean.dtype
    z = jnp.zeros((B, F), dtype)
    acc = _Acc(
        jnp.zeros((B,), dtype),
        jnp.zeros((B,), dtype),
        z,
        z,
        z,
        z,
        jnp.full((B, F), -1, jnp.int32),
    )
    return _Carry(jnp.zeros((n, B), dtype), batch.init, acc)


def _segment_length(N: int, config: TuneConfig) -> int:
    if config.segment is not None:
        return int(min(config.segment, N))
    return max(1, int(math.ceil(math.sqrt(N))))


def _run(problem: Problem, config: TuneConfig, c: Constrained, params, batch, carry):
    """Scan the fused step over all samples (nested, checkpointed scan)."""
    N = problem.num_steps
    L = _segment_length(N, config)
    S, rem = divmod(N, L)
    data = batch.data

    def body(cc, xs):
        if data is None:
            k = xs
            u, x, y, code = _truth(problem, batch, cc.x, k)
            cc = cc._replace(x=x)
        else:
            k, u, y, code = xs
        return _step(problem, config, c, params, cc, k, u, y, code)[0], None

    def segment(cr, xs):
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
    fn = _truth_scan(problem)
    x = jnp.zeros((n, B), dtype)
    us, ys, codes = [], [], []
    for k0 in range(0, problem.num_steps, chunk):
        ks = jnp.arange(k0, min(k0 + chunk, problem.num_steps), dtype=jnp.int32)
        x, (u, y, code) = fn(batch, x, ks)
        us.append(u)
        ys.append(y)
        codes.append(code)
    data = Observed(jnp.concatenate(us), jnp.concatenate(ys), jnp.concatenate(codes))
    return batch._replace(data=data)


def _truth_scan(problem: Problem):
    @jax.jit
    def fn(batch, x, ks):
        def body(xc, k):
            u, xn, y, code = _truth(problem, batch, xc, k)
            return xn, (u, y, code)

        return jax.lax.scan(body, x, ks)

    return fn


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
    delay = jnp.mean(jnp.sum(a.delay, axis=-1)) * problem.dt
    false = jnp.mean(jnp.sum(-a.log_nofalse, axis=-1))
    w = jnp.asarray(config.weights if weights is None else weights, dtype)
    total = (w[0] * ce + w[1] * delay + w[2] * false).astype(dtype)
    return total, LossParts(total, ce, delay, false, a.decl_step)


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


# --------------------------------------------------------------------------------------
# Hard metrics of a batch (the exact rule)
# --------------------------------------------------------------------------------------


def hard_metrics(problem: Problem, batch: TrainingBatch, decl_step: np.ndarray) -> dict:
    """Detection, isolation and false declarations of a batch from hard declaration steps.

    A declaration of ``j`` is correct when ``j`` is present in the truth at that step
    (as in :func:`uimm_jax.runner.summarize`).

    Args:
        problem: the :class:`Problem`.
        batch: the :class:`TrainingBatch`.
        decl_step: ``(B, F)`` declaration steps (``LossParts.decl_step``).

    Returns:
        dict with ``detection_rate``, ``false_runs`` (runs with a false declaration),
        ``median_delay_s`` per fault and ``runs``.
    """
    on = np.asarray(batch.onset).astype(np.int64)
    de = np.asarray(decl_step).astype(np.int64)
    has = on < _NEVER
    det = has & (de >= on)
    false = (de >= 0) & (~has | (de < on))
    names = problem.diagnoser.table.names
    delays = {}
    for j, f in enumerate(names):
        d = (de[det[:, j], j] - on[det[:, j], j]) * problem.dt
        if has[:, j].any():
            delays[f] = float(np.median(d)) if d.size else None
    return {
        "runs": int(on.shape[0]),
        "events": int(has.sum()),
        "detection_rate": float(det.sum() / max(has.sum(), 1)),
        "false_runs": int(np.any(false, axis=1).sum()),
        "median_delay_s": delays,
    }


# --------------------------------------------------------------------------------------
# The optax loop
# --------------------------------------------------------------------------------------


class FitResult(NamedTuple):
    """Outcome of :func:`fit`.

    Attributes:
        params: the best :class:`TunableParams` seen (lowest loss).
        last_params: the parameters after the last iteration.
        history: ``(K,)`` loss (with the final weights) at each iteration, before its
            update.
        parts: list of per-iteration dicts (loss parts and hard batch metrics).
        best_iteration: index of the best loss.
        runtime_s: wall time of the loop.
    """

    params: TunableParams
    last_params: TunableParams
    history: np.ndarray
    parts: list
    best_iteration: int
    runtime_s: float


def fit(
    problem: Problem,
    batch: TrainingBatch,
    init: TunableParams,
    config: TuneConfig,
    *,
    iters: int = 50,
    optimizer=None,
    learning_rate: float = 0.05,
    warmup: int = 0,
    progress: bool | Callable[[int, dict], None] = False,
) -> FitResult:
    """Minimise the tuning loss with optax (adam by default) on a fixed batch.

    The batch's noise keys are fixed: every iteration sees the same runs (common random
    numbers), so the loss is a deterministic function of the parameters.

    Args:
        problem: the :class:`Problem` (from :func:`make_batch`).
        batch: the :class:`TrainingBatch`.
        init: starting :class:`TunableParams` (:func:`init_params`).
        config: :class:`TuneConfig`.
        iters: optimiser iterations.
        optimizer: an ``optax.GradientTransformation`` (default ``optax.adam``).
        learning_rate: adam's learning rate when ``optimizer`` is None.
        warmup: first iterations on the cross-entropy alone (decision weights 0): the
            transition matrix becomes sticky before the decision terms act; the best
            parameters are chosen among the iterations after it (or the last one).
        progress: ``True`` prints one line per iteration to stderr; a callable gets
            ``(iteration, info)``.

    Returns:
        A :class:`FitResult`.
    """
    import sys

    import optax

    opt = optimizer if optimizer is not None else optax.adam(learning_rate)
    _, vg = make_loss_fn(problem, config)
    update = jax.jit(opt.update)
    params = init
    state = opt.init(params)
    history, parts_log = [], []
    best, best_loss, best_it = params, np.inf, 0
    t0 = time.perf_counter()
    M = problem.num_models
    w_full = np.asarray(config.weights, np.float64)
    for it in range(iters):
        w_it = w_full * (np.array([1.0, 0.0, 0.0]) if it < warmup else 1.0)
        (loss, parts), grads = vg(params, batch, w_it)
        # The history is the loss with the final weights (the ramp only steers the steps).
        loss_f = float(w_full @ np.array([float(parts.ce), float(parts.delay), float(parts.false)]))
        if not np.isfinite(float(loss)) or not all(
            bool(jnp.all(jnp.isfinite(g))) for g in jax.tree.leaves(grads)
        ):
            raise FloatingPointError(f"fit: non-finite loss or gradient at iteration {it}")
        hm = hard_metrics(problem, batch, np.asarray(parts.decl_step))
        s = settings_from_params(params, M, config)
        info = {
            "iteration": it,
            "loss": loss_f,
            "ce": float(parts.ce),
            "delay_s": float(parts.delay),
            "false": float(parts.false),
            "threshold": s["threshold"],
            "hold": s["hold_real"],
            "min_stay": float(np.min(np.diag(s["transition"]))),
            "elapsed_s": time.perf_counter() - t0,
            **{f"hard_{k}": v for k, v in hm.items()},
        }
        history.append(loss_f)
        parts_log.append(info)
        if (it >= warmup or it == iters - 1) and loss_f < best_loss:
            best, best_loss, best_it = params, loss_f, it
        if progress is True:
            print(
                f"  iter {it:4d}  loss {loss_f:10.5g}  ce {info['ce']:9.4g}  "
                f"delay {info['delay_s']:8.4g} s  false {info['false']:7.4g}  "
                f"thr {s['threshold']:.6f}  hold {s['hold_real']:7.2f}  "
                f"min stay {info['min_stay']:.6f}  hard: det {hm['detection_rate']:.2f} "
                f"false runs {hm['false_runs']}  ({info['elapsed_s']:.0f} s)",
                file=sys.stderr,
                flush=True,
            )
        elif callable(progress):
            progress(it, info)
        updates, state = update(grads, state, params)
        params = optax.apply_updates(params, updates)
    return FitResult(
        best,
        params,
        np.asarray(history),
        parts_log,
        best_it,
        time.perf_counter() - t0,
    )


# --------------------------------------------------------------------------------------
# Writing tuned settings
# --------------------------------------------------------------------------------------


def rescale_scenario(scenario, duration: float):
    """The scenario with another duration, its event times scaled by the same factor.

    Args:
        scenario: a :class:`~uimm_jax.scenarios.Scenario`.
        duration: the new duration in s (a whole number of samples).

    Returns:
        A validated :class:`~uimm_jax.scenarios.Scenario` (the same object if unchanged).
    """
    from uimm_jax.scenario.parse import parse_scenario
    from uimm_jax.scenario.write import scenario_to_dict

    if float(duration) == float(scenario.duration):
        return scenario
    d = scenario_to_dict(scenario)
    f = float(duration) / float(scenario.duration)
    d["duration"] = float(duration)
    for ev in d.get("events", []):
        ev["time"] = float(ev["time"]) * f
    return parse_scenario(d, source=f"{scenario.source} (rescaled to {duration:g} s)")


def _sweep_cases(scenarios) -> list[dict]:
    cases, names = [], set()
    for s in scenarios:
        if not s.events:
            continue
        name = s.name if s.name not in names else f"{s.name}-{len(names)}"
        names.add(name)
        cases.append(
            {
                "name": name,
                "events": [
                    {"fault": e.fault, "time": float(e.time), "magnitude": float(e.magnitude)}
                    for e in s.events
                ],
            }
        )
    return cases


def evaluate(
    scenario, extra=(), *, runs: int = 200, seed: int = 0, progress=False, cases_from=None
) -> dict:
    """Monte Carlo metrics of a scenario's filter settings with the exact hard rule.

    Runs :func:`uimm_jax.montecarlo.run_sweep` on the scenario's events, the events of
    each ``extra`` scenario (same fault library) and the fault-free case.  ``cases_from``
    (a list of scenarios) replaces ``[scenario, *extra]`` as the source of the cases'
    events and names, so that two settings can be compared on identical, identically
    named cases.

    Returns:
        dict ``case -> metrics`` with, per case, ``runs``, ``all_correct`` (fraction of
        runs in which every fault event is correctly declared and isolated -- the first
        declaration after its onset names it, see :meth:`SweepResult.isolated` -- and
        nothing is falsely declared), ``detection`` and ``median_delay_s`` per fault,
        ``isolation_accuracy``, ``runs_with_false_declaration``, ``false_declarations``
        and ``mode_accuracy``; plus ``"_sweep"`` with the sweep's run-steps and runtime.
    """
    from uimm_jax.montecarlo import run_sweep

    res = run_sweep(
        scenario,
        runs=runs,
        seed=seed,
        methods=("uimm",),
        cases=_sweep_cases([scenario, *extra] if cases_from is None else cases_from),
        fault_free=True,
        progress=progress,
    )
    det = res.detected()
    false = res.false_declared()
    isolated = res.isolated()
    has = res.onset_step >= 0
    out = {}
    for cell, summ in zip(res.cells, res.summaries, strict=True):
        i = cell.index
        ok = np.all(det[i] | ~has[i], axis=-1) & ~np.any(false[i], axis=-1) & isolated[i]
        out[cell.case] = {
            "runs": int(summ["runs"]),
            "all_correct": float(np.mean(ok)),
            "detection": summ["detection_probability"],
            "median_delay_s": summ["median_delay_s"],
            "isolation_accuracy": summ["isolation_accuracy"],
            "runs_with_false_declaration": int(summ["runs_with_false_declaration"]),
            "false_declarations": int(summ["false_declarations"]),
            "mode_accuracy": float(summ["mode_accuracy"]),
        }
    out["_sweep"] = {"run_steps": int(res.run_steps), "runtime_s": float(res.runtime_s)}
    return out


def _fmt(v, scale=1.0, digits=4) -> str:
    if v is None:
        return "never"
    return f"{v * scale:.{digits}g}"


def before_after_table(before: dict, after: dict) -> str:
    """A Markdown table comparing two :func:`evaluate` results."""
    rows = [("metric (held-out runs)", "before", "after")]
    for case, b in before.items():
        if case.startswith("_"):
            continue
        a = after[case]
        rows.append((f"{case}: runs", str(b["runs"]), str(a["runs"])))
        if b["detection"]:
            rows.append(
                (
                    f"{case}: every fault declared and isolated, no false declaration",
                    _fmt(b["all_correct"]),
                    _fmt(a["all_correct"]),
                )
            )
            for f in b["detection"]:
                rows.append(
                    (
                        f"{case}: {f} detected",
                        _fmt(b["detection"][f]),
                        _fmt(a["detection"][f]),
                    )
                )
                rows.append(
                    (
                        f"{case}: {f} median delay (ms)",
                        _fmt(b["median_delay_s"][f], 1e3),
                        _fmt(a["median_delay_s"][f], 1e3),
                    )
                )
            rows.append(
                (
                    f"{case}: isolation accuracy",
                    _fmt(b["isolation_accuracy"]),
                    _fmt(a["isolation_accuracy"]),
                )
            )
        rows.append(
            (
                f"{case}: runs with a false declaration",
                str(b["runs_with_false_declaration"]),
                str(a["runs_with_false_declaration"]),
            )
        )
        rows.append((f"{case}: mode accuracy", _fmt(b["mode_accuracy"]), _fmt(a["mode_accuracy"])))
    w = [max(len(r[i]) for r in rows) for i in range(3)]
    lines = []
    for n, r in enumerate(rows):
        lines.append(f"| {r[0]:<{w[0]}} | {r[1]:>{w[1]}} | {r[2]:>{w[2]}} |")
        if n == 0:
            lines.append(f"|{'-' * (w[0] + 2)}|{'-' * (w[1] + 1)}:|{'-' * (w[2] + 1)}:|")
    return "\n".join(lines)


def before_after(
    before_scenario, after_scenario, extra=(), *, runs=200, seed=0, progress=False, before=None
):
    """Evaluate two settings on the same held-out runs: ``(markdown_table, record)``.

    ``extra`` scenarios contribute their events as further cases; they are evaluated with
    the settings of ``before_scenario`` / ``after_scenario`` (only their events are used).
    ``before`` is an earlier :func:`evaluate` result of ``before_scenario`` on the same
    cases, runs and seed, reused instead of running that sweep again.
    """
    # Both settings run on the cases (events, names) of ``before_scenario`` and ``extra``.
    cases = [before_scenario, *extra]
    b = before
    if b is None:
        b = evaluate(before_scenario, runs=runs, seed=seed, progress=progress, cases_from=cases)
    a = evaluate(after_scenario, runs=runs, seed=seed, progress=progress, cases_from=cases)
    return before_after_table(b, a), {"before": b, "after": a, "seed": seed, "runs": runs}


def tuned_scenario(scenario, settings: Mapping[str, Any], *, name: str | None = None) -> dict:
    """The scenario's dict (:func:`~uimm_jax.scenarios.scenario_to_dict`) with tuned settings.

    The transition matrix is written in full (``[filter].transition``, rows renormalised
    in float64 so that they sum to 1 within the file's tolerance), with the threshold and
    the integer hold in ``[filter.decision]``.  Noise scales are not written (the
    scenario's ``[noise]`` is also the truth's).

    Args:
        scenario: the source scenario.
        settings: :func:`settings_from_params` output.
        name: the new scenario name (default: ``<name>-tuned``, or the name unchanged if
            it already ends in ``-tuned``, so that tuning a tuned file again does not stack
            suffixes).

    Returns:
        A dict for :func:`~uimm_jax.scenarios.parse_scenario` / ``dump_scenario``.
    """
    from uimm_jax.scenario.write import scenario_to_dict

    d = scenario_to_dict(scenario)
    P = np.asarray(settings["transition"], np.float64)
    P = P / P.sum(axis=1, keepdims=True)
    flt = d["filter"]
    flt.pop("stay", None)
    flt["transition"] = [[float(v) for v in row] for row in P]
    mu0 = np.asarray(scenario.initial_mode_probs(), np.float64)
    flt["initial_mode_probs"] = [float(v) for v in mu0 / mu0.sum()]
    flt.setdefault("decision", {})
    flt["decision"]["threshold"] = float(settings["threshold"])
    flt["decision"]["hold"] = int(settings["hold"])
    default = scenario.name if scenario.name.endswith("-tuned") else f"{scenario.name}-tuned"
    d["name"] = name or default
    return d
