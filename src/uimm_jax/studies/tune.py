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
of its own objective (checked against finite differences in ``tests/studies/test_tuning.py``).
With ``couple=True`` the whole loss is differentiated with respect to every parameter.
Measured on paper simulation 1 from the paper's settings, the coupled gradient makes the
chain *less* sticky (the cheapest way to shrink the false-declaration hazard) until
nothing is ever declared, a flat region of the delay surrogate; the decoupled one makes
the chain sticky (cross-entropy) while raising the threshold and the persistence.

**Long runs.**  The time loop is a nested ``lax.scan``: the outer scan runs segments of
``segment`` steps (``sqrt(N) / 4`` by default), each segment ``jax.checkpoint``-ed: it
simulates its samples' truth into a segment-sized buffer, then scans the diagnoser +
surrogate step over the buffer.  Reverse mode stores one carry per
segment and recomputes one segment at a time: memory ``O(sqrt(N))``.  The measurement
update's reverse mode is written by hand (:func:`uimm_jax.engine.kalman.kf_update`), so
no ``lax.cond`` of the update and no unrolled factorisation is differentiated (see
``benchmarks/bench_gradient.py`` and ``docs/tuning.md`` for measured figures).  The truth
is simulated inside the loop, step ``k``'s noise a function of the key and ``k``
(:func:`uimm_jax.engine.noise.standard_noise`; only one segment's samples are held).

**Evaluation** always uses the exact hard rule: :func:`hard_metrics` reads the hard
declarations of the training forward pass, and :func:`evaluate` / :func:`before_after`
(used by the CLI, :mod:`uimm_jax.cli.tune`) run :func:`uimm_jax.studies.sweep.run_sweep` on
held-out seeds.

**Modules.**  The parameters and their constraints live in
:mod:`uimm_jax.studies.tune_params`, the training batches and the loss in
:mod:`uimm_jax.studies.tune_loss`, the hard-rule evaluation and the tuned scenario in
:mod:`uimm_jax.studies.tune_eval`; this module holds the optax loop (:func:`fit`) and
re-exports the public names of all three.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.studies.tune_eval import (
    before_after,
    before_after_table,
    evaluate,
    hard_metrics,
    rescale_scenario,
    tuned_scenario,
)
from uimm_jax.studies.tune_loss import (
    LossParts,
    Observed,
    Problem,
    RunCase,
    TrainingBatch,
    loss_and_parts,
    make_batch,
    make_loss_fn,
    precompute_truth,
    scenario_case,
    trace_surrogate,
)
from uimm_jax.studies.tune_params import (
    STRUCTURES,
    Constrained,
    LossWeights,
    TunableParams,
    TuneConfig,
    constrain,
    diag_params,
    hard_hold,
    init_params,
    settings_from_params,
)

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
    "scenario_case",
    "settings_from_params",
    "trace_surrogate",
    "tuned_scenario",
]


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
