"""From a scenario to a diagnosis: build the bank, simulate the truth, filter, summarise.

* :func:`setup_scenario` builds (and caches) the diagnoser, its parameters and the truth
  plan from a :class:`~uimm_jax.scenario.spec.Scenario`.
* :func:`simulate_scenario` runs the truth (one ``lax.scan``, chunked).
* :func:`filter_measurements` runs the diagnoser over measurements (one ``lax.scan``,
  chunked) -- simulated ones or a user's own data.
* :func:`run_scenario` does both and returns a :class:`RunResult` with a summary dict
  (:func:`summarize`, with the definitions of :mod:`uimm_jax.engine.metrics`);
  :func:`execute_run` is that flow for any diagnose function (the float32 option uses it).

The truth plan comes from :func:`uimm_jax.studies.truth.build_truth_plan`, the time loops
from :mod:`uimm_jax.engine.scan` (:func:`~uimm_jax.engine.scan.truth_scan`,
:func:`~uimm_jax.engine.scan.filter_chunk`, driven by
:func:`~uimm_jax.engine.scan.scan_chunked`).

Time convention: sample k is taken at ``t_k = (k + 1) dt``; the input ``u_k = u(k dt)`` is
held over ``[k dt, (k+1) dt)``; an event at time ``T`` acts from step ``round(T / dt)``.
"""

from __future__ import annotations

import dataclasses
import functools
import time
import warnings
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax._checks import check_positive_int, check_seed
from uimm_jax.engine import metrics
from uimm_jax.engine.bank import FaultTable, fault_table
from uimm_jax.engine.scan import (
    ESTIMATE_OUTPUTS,
    FILTER_OUTPUTS,
    filter_chunk,
    scan_chunked,
    truth_scan,
)
from uimm_jax.engine.truth import InputSignal, TruthPlan
from uimm_jax.engine.uimm import Diagnoser, DiagParams, make_params
from uimm_jax.engine.uimm_est import Z95, UIMMEstDiagnoser, build_diagnoser
from uimm_jax.errors import UIMMWarning
from uimm_jax.plants.dynamics import make_dynamics
from uimm_jax.scenario.spec import same_bank
from uimm_jax.studies.checks import check_run_data, check_setup_args
from uimm_jax.studies.measured import truth_for_measurements
from uimm_jax.studies.truth import (
    build_truth_plan,
    scenario_inputs,
    scenario_onsets,
    scenario_ramps,
)

__all__ = [
    "RunResult",
    "RunSetup",
    "execute_run",
    "filter_measurements",
    "run_fdi_counts",
    "run_scenario",
    "setup_scenario",
    "simulate_scenario",
    "summarize",
    "true_set_probabilities",
]

DEFAULT_CHUNK = 100_000


@dataclasses.dataclass(frozen=True, eq=False)
class RunSetup:
    """A scenario compiled into engine objects.

    Attributes:
        scenario: the source scenario.
        method: ``"uimm"`` or ``"imm"``.
        diagnoser: the :class:`~uimm_jax.engine.uimm.Diagnoser` (static).
        params: its :class:`~uimm_jax.engine.uimm.DiagParams`.
        init_state: initial diagnoser state (one run).
        signal: the :class:`~uimm_jax.engine.truth.InputSignal`.
        plan: the truth :class:`~uimm_jax.engine.truth.TruthPlan`.
        table: the fault table of the bank.
        event_steps: step of each truth event.
        transition: the host transition matrix used.
        initial_mode_probs: the host initial mode probabilities used.
    """

    scenario: Any
    method: str
    diagnoser: Diagnoser
    params: DiagParams
    init_state: Any
    signal: InputSignal
    plan: TruthPlan
    table: FaultTable
    event_steps: np.ndarray
    transition: np.ndarray
    initial_mode_probs: np.ndarray


@functools.lru_cache(maxsize=64)
def _cached_diagnoser(plant, dt, method, gate, faults_key, nominal_key, est=None):
    nominal = np.asarray(nominal_key)
    faults = {k: dict(v) for k, v in faults_key}
    table = fault_table(plant.param_names, nominal, faults, log_params=plant.positive_params)
    refs = [nominal] + [
        table.theta_numpy(np.eye(table.num_faults, dtype=bool)[j]) for j in range(table.num_faults)
    ]
    dyn = make_dynamics(plant, dt, np.array(refs))
    return build_diagnoser(method, dyn, table, gate=gate, settings=est), table


def resolve_filter_settings(scenario, method: str) -> tuple[np.ndarray, np.ndarray]:
    """Transition matrix and initial mode probabilities for ``method``.

    When ``method``'s bank differs from the scenario's method's (``"imm"`` against
    ``"uimm"`` or ``"uimm-est"``) and the scenario gives them in full for its own method,
    they are adapted with a warning: the stay probability becomes the mean of the given
    diagonal and model 0 keeps the given first probability, the rest being shared equally.
    """
    flt = scenario.filter
    M = scenario.num_models(method)
    own = same_bank(method, flt.method)  # uimm and uimm-est share the bank's layout
    if own or flt.transition is None:
        P = scenario.transition_matrix(method)
    else:
        stay = float(np.mean(np.diag(flt.transition)))
        warnings.warn(
            f"[filter].transition is written for {flt.method!r}; for {method!r} "
            f"({M} models) the stay probability {stay:.6g} (its mean diagonal) is "
            "used",
            UIMMWarning,
            stacklevel=3,
        )
        P = np.full((M, M), (1 - stay) / max(M - 1, 1))
        np.fill_diagonal(P, stay)
    if own or flt.initial_mode_probs is None:
        mu0 = scenario.initial_mode_probs(method)
    else:
        p0 = float(flt.initial_mode_probs[0])
        mu0 = np.full(M, (1 - p0) / max(M - 1, 1))
        mu0[0] = p0
        warnings.warn(
            f"[filter].initial_mode_probs is written for {flt.method!r}; for "
            f"{method!r} model 0 keeps {p0:.6g} and the rest is shared equally",
            UIMMWarning,
            stacklevel=3,
        )
    return P, mu0


def setup_scenario(
    scenario, method: str | None = None, *, dtype=None, magnitude_scale: float = 1.0
) -> RunSetup:
    """Compile a scenario into a :class:`RunSetup` (diagnoser cached across calls).

    Args:
        scenario: a :class:`~uimm_jax.scenario.spec.Scenario`.
        method: ``"uimm"`` or ``"imm"``; default: the scenario's.
        dtype: float dtype (default: JAX's default float; float64 with x64 enabled).
        magnitude_scale: multiplies every event's magnitude (truth only).
    """
    check_setup_args(scenario, method, dtype, magnitude_scale)
    dtype = dtype or jnp.asarray(0.0).dtype
    method = method or scenario.filter.method
    plant = scenario.plant
    nominal = plant.theta(scenario.plant_params)
    faults_key = tuple((k, tuple(sorted(v.items()))) for k, v in scenario.faults.items())
    gate = scenario.filter.gate
    diag, table = _cached_diagnoser(
        plant,
        float(scenario.dt),
        method,
        gate,
        faults_key,
        tuple(nominal.tolist()),
        scenario.filter.est if method == UIMMEstDiagnoser.method else None,  # [filter.est]
    )
    P, mu0 = resolve_filter_settings(scenario, method)
    flt = scenario.filter
    params = make_params(
        P,
        scenario.process_noise,
        scenario.measurement_noise,
        flt.decision.threshold,
        flt.decision.hold,
        dtype,
    )
    init = diag.init(np.asarray(flt.initial_mean), np.asarray(flt.initial_cov), mu0, (), dtype)
    # Truth plan: phase 0 nominal, then one phase per event (faults accumulate).
    onset, magnitude, steps = scenario_onsets(scenario, table.names, magnitude_scale)
    ramp, end, growth = scenario_ramps(scenario, table.names)
    plan = build_truth_plan(
        scenario, diag.dyn, table, onset, magnitude, dtype=dtype, ramp=ramp, end=end, growth=growth
    )
    return RunSetup(
        scenario,
        method,
        diag,
        params,
        init,
        InputSignal.from_spec(scenario.input, dtype),
        plan,
        table,
        steps,
        P,
        mu0,
    )


# --------------------------------------------------------------------------------------
# Time loops (module-level jitted chunk functions: cached across calls)
# --------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("dyn", "dt", "p"))
def _sim_chunk(dyn, plan, signal, key, x, k0, ks, dt, p):
    del k0
    return truth_scan(dyn, dt, p, plan, signal, key, x, ks)


def simulate_scenario(
    setup: RunSetup,
    seed: int | None = None,
    *,
    chunk: int = DEFAULT_CHUNK,
    progress: Callable | None = None,
) -> dict[str, np.ndarray]:
    """Simulate the truth of a scenario.

    Returns:
        dict with ``u`` (N, p), ``x`` (N, n), ``y`` (N, m), ``truth`` (N,) fault-set codes
        and ``t`` (N,) sample times.
    """
    sc = setup.scenario
    seed = sc.seed if seed is None else int(seed)
    key = jax.random.PRNGKey(seed)
    n = sc.plant.state_dim
    p = sc.plant.input_dim
    dtype = setup.params.imm.Q.dtype
    x0 = jnp.zeros((n,), dtype)
    dyn = setup.diagnoser.dyn
    run = lambda c, k0, ks: _sim_chunk(
        dyn, setup.plan, setup.signal, key, c, k0, ks, float(sc.dt), p
    )
    _, (u, x, y, code) = scan_chunked(run, x0, sc.num_steps, chunk=chunk, progress=progress)
    u = np.repeat(u[:, None], p, axis=1)
    t = (np.arange(sc.num_steps) + 1) * sc.dt
    bad = ~(np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(y), axis=1))
    if bad.any():
        # A diverged truth would reach the filter as NaN measurements, i.e. "missing".
        k = int(np.argmax(bad))
        raise ValueError(
            f"{sc.source}: the simulated truth is not finite from t = {t[k]:g} s (sample {k}): "
            "the plant diverges with these parameters; check [plant.params], the fault "
            "values and [[events]].magnitude."
        )
    return {"u": u, "x": x, "y": y, "truth": code, "t": t}


def filter_measurements(
    setup: RunSetup,
    y,
    u=None,
    *,
    chunk: int = DEFAULT_CHUNK,
    with_cov: bool = False,
    progress: Callable | None = None,
    timings: list | None = None,
):
    """Run the scenario's diagnoser over measurements ``y`` (N, m) and inputs ``u`` (N, p).

    ``u`` defaults to the scenario's input signal.

    Returns:
        ``(final_state, outputs)`` with outputs a dict of per-step NumPy arrays:
        ``mode_probs`` (N, M), ``mean`` (N, n), ``recognised`` (N,), ``declared`` (N,),
        ``health`` (N,), ``nis`` (N,) and ``nis_channels`` (N, m) (the innovation check:
        :data:`~uimm_jax.engine.scan.FILTER_OUTPUTS`) and, with ``with_cov``, ``cov`` (N, n,
        n).  ``timings``, if given, receives ``(steps, seconds)`` per chunk (the first
        includes compilation).
    """
    sc = setup.scenario
    y, u = check_run_data(setup, y, u, chunk)
    dtype = setup.params.imm.Q.dtype
    ys = jnp.asarray(y, dtype)
    N = ys.shape[0]
    us = jnp.asarray(scenario_inputs(sc, N) if u is None else u, dtype)
    keys = FILTER_OUTPUTS + (("cov",) if with_cov else ())
    if isinstance(setup.diagnoser, UIMMEstDiagnoser):
        keys += ESTIMATE_OUTPUTS
    run = lambda c, k0, uy: filter_chunk(setup.diagnoser, setup.params, c, k0, uy, keys)
    final, out = scan_chunked(
        run, setup.init_state, N, chunk=chunk, xs=(us, ys), progress=progress, timings=timings
    )
    return final, dict(zip(keys, out, strict=True))


@dataclasses.dataclass
class RunResult:
    """Everything a scenario run produced.

    Attributes:
        setup: the :class:`RunSetup`.
        truth: output of :func:`simulate_scenario`.
        outputs: per-step filter outputs (see :func:`filter_measurements`).
        summary: the machine-readable summary (:func:`summarize`).
    """

    setup: RunSetup
    truth: dict[str, np.ndarray]
    outputs: dict[str, np.ndarray]
    summary: dict[str, Any]


def run_scenario(
    scenario,
    method: str | None = None,
    seed: int | None = None,
    *,
    chunk: int = DEFAULT_CHUNK,
    progress: Callable | None = None,
    measurements=None,
) -> RunResult:
    """Simulate a scenario's truth and diagnose it (or diagnose given measurements).

    Args:
        scenario: the :class:`~uimm_jax.scenario.spec.Scenario`.
        method: ``"uimm"`` or ``"imm"``; default: the scenario's.
        seed: PRNG seed of the truth noise; default: the scenario's.
        chunk: steps per compiled chunk (progress granularity and memory bound).
        progress: optional ``(stage, done, total, elapsed)`` callback.
        measurements: optional measured data to diagnose instead of simulating: an
            ``(N, m)`` array or a :class:`~uimm_jax.scenario.measured.MeasuredData` (whose inputs,
            if any, are used); the truth fields of the summary then follow the scenario's
            events and the true states are NaN.

    Returns:
        A :class:`RunResult`.
    """
    check_seed(seed)
    check_positive_int(chunk, "chunk")
    setup = setup_scenario(scenario, method)
    return execute_run(
        setup,
        filter_measurements,
        seed=seed,
        chunk=chunk,
        progress=progress,
        measurements=measurements,
    )


def execute_run(
    setup: RunSetup,
    diagnose: Callable,
    *,
    truth_setup: RunSetup | None = None,
    seed: int | None = None,
    chunk: int = DEFAULT_CHUNK,
    progress: Callable | None = None,
    measurements=None,
) -> RunResult:
    """Simulate (or read) a run's truth, diagnose it and summarise it.

    Args:
        setup: the :class:`RunSetup` of the diagnoser (and of the summary).
        diagnose: ``diagnose(setup, y, u, *, chunk, progress, timings) -> (state,
            outputs)``, e.g. :func:`filter_measurements`.
        truth_setup: the setup whose truth is simulated (default ``setup``).
        seed: PRNG seed of the truth noise; default: the scenario's.
        chunk: steps per compiled chunk.
        progress: optional ``(stage, done, total, elapsed)`` callback.
        measurements: optional measured data instead of a simulated truth.

    Returns:
        A :class:`RunResult`.
    """
    scenario = setup.scenario
    cb = (
        (lambda stage: lambda d, t, e: progress(stage, d, t, e))
        if progress
        else (lambda stage: None)
    )
    t0 = time.perf_counter()
    if measurements is None:
        truth = simulate_scenario(truth_setup or setup, seed, chunk=chunk, progress=cb("simulate"))
    else:  # measured data: no simulation; inputs from the data when it has them
        truth = truth_for_measurements(setup, measurements, scenario_inputs)
    t_sim = time.perf_counter() - t0
    t1 = time.perf_counter()
    timings: list = []
    _, outputs = diagnose(
        setup, truth["y"], truth["u"], chunk=chunk, progress=cb("filter"), timings=timings
    )
    t_filter = time.perf_counter() - t1
    summary = summarize(
        setup,
        truth["truth"],
        outputs,
        runtime_s=t_filter,
        sim_runtime_s=t_sim,
        seed=scenario.seed if seed is None else int(seed),
        chunk_timings=timings,
    )
    return RunResult(setup, truth, outputs, summary)


def _rates(N: int, runtime_s: float, chunk_timings: list | None) -> dict[str, Any]:
    """``steps_per_s`` (steady state when chunk timings allow) and ``compile_s``."""
    if chunk_timings and len(chunk_timings) > 1:
        steps = sum(n for n, _ in chunk_timings[1:])
        secs = sum(t for _, t in chunk_timings[1:])
        rate = steps / secs if secs > 0 else None
        first_n, first_t = chunk_timings[0]
        compile_s = max(first_t - first_n / rate, 0.0) if rate else None
        return {"steps_per_s": rate, "compile_s": compile_s}
    return {"steps_per_s": float(N / runtime_s) if runtime_s > 0 else None, "compile_s": None}


def true_set_probabilities(
    setup: RunSetup, truth_codes, outputs: dict, *, chunk: int = 65_536
) -> np.ndarray:
    """``(N,)`` mode probability the bank gave to the true fault set at each sample.

    The mode probabilities of step ``k`` refer to the bank of the declared set before
    that step (for UIMM, ``[D, D+f1, ...]`` with ``D`` declared up to step ``k - 1``).
    """
    F = setup.table.num_faults
    declared = np.asarray(outputs["declared"]).astype(np.int64)
    before = np.concatenate([np.zeros(1, np.int64), declared[:-1]])
    truth = np.asarray(truth_codes)
    probs = np.asarray(outputs["mode_probs"])
    out = np.zeros(truth.shape[0], probs.dtype)
    for k in range(0, truth.shape[0], chunk):  # bounded memory for large banks
        sl = slice(k, k + chunk)
        sets = ((before[None, sl] >> np.arange(F)[:, None]) & 1).astype(bool)  # (F, L)
        with np.errstate(divide="ignore"):
            log_p = jnp.asarray(np.log(probs[sl].T))
        lp = setup.diagnoser.true_set_log_prob(log_p, jnp.asarray(sets), truth[sl])
        out[sl] = np.exp(np.asarray(lp))
    return out


def run_fdi_counts(setup: RunSetup, truth_codes, outputs: dict) -> metrics.FDICounts:
    """The :class:`~uimm_jax.engine.metrics.FDICounts` of one run, summed over its samples."""
    terms = metrics.fdi_terms(
        jnp.asarray(np.asarray(truth_codes)),
        jnp.asarray(np.asarray(outputs["declared"])),
        jnp.asarray(true_set_probabilities(setup, truth_codes, outputs)),
    )
    return metrics.FDICounts(*(np.sum(np.asarray(t)) for t in terms))


def decision_changes(outputs: dict, truth_codes, names, dt: float, hold: int = 0) -> dict[str, Any]:
    """Declarations and retractions of a run from its declared-set codes, with sizes.

    Every switch on of fault ``j`` at step ``k`` is a declaration (*correct* when ``j`` is
    in the truth at ``k``), every switch off a retraction (*correct* when ``j`` is no longer
    in the truth: the fault had ended).  With per-step ``magnitude`` and ``magnitude_sd``
    outputs (a size-estimating diagnoser) a declaration carries the estimate and its 95 %
    interval at the end of the run; if it was retracted, ``hold + 1`` samples before the
    retraction, when the retraction rule began to count (after that the estimate follows
    the fault's end; ``hold``: the samples that rule counts, uimm-est's ``retract_hold``
    or the filter's ``hold``).

    Returns:
        ``{"declarations": [...], "retractions": [...]}``; the declarations only when the
        outputs have magnitudes (else the caller's list stands).
    """
    codes = np.asarray(outputs["declared"], np.int64)
    truth = np.asarray(truth_codes, np.int64)
    prev = np.concatenate([[0], codes[:-1]])
    decl, retr = [], []
    mag = outputs.get("magnitude")
    sd = outputs.get("magnitude_sd")
    for j, name in enumerate(names):
        bit = 1 << j
        on = np.flatnonzero((codes & bit) & ~(prev & bit))
        off = np.flatnonzero(~(codes & bit) & (prev & bit))
        for k in on:
            entry = {"fault": name, "time": float((k + 1) * dt), "correct": bool(truth[k] & bit)}
            if mag is not None:
                later = off[off > k]
                last = max(int(later[0]) - 1 - hold, k) if later.size else len(codes) - 1
                m, s_ = float(mag[last, j]), float(sd[last, j])
                entry |= {"magnitude": m, "magnitude_ci": [m - Z95 * s_, m + Z95 * s_]}
            decl.append(entry)
        retr += [
            {"fault": name, "time": float((k + 1) * dt), "correct": not bool(truth[k] & bit)}
            for k in off
        ]
    out: dict[str, Any] = {"retractions": sorted(retr, key=lambda d: d["time"])}
    if mag is not None:
        out["declarations"] = sorted(decl, key=lambda d: d["time"])
    return out


def summarize(
    setup: RunSetup,
    truth_codes: np.ndarray,
    outputs: dict,
    *,
    runtime_s: float,
    sim_runtime_s: float | None = None,
    seed: int | None = None,
    chunk_timings: list | None = None,
) -> dict[str, Any]:
    """The machine-readable summary of one run (written as ``summary.json`` by the CLI).

    A declaration of fault j at step k is *correct* when fault j is present in the truth at
    step k, otherwise it is a *false declaration*.  ``detection_delay_s[f]`` is the time
    from the event of f to its first correct declaration (``None`` if never declared).
    ``mode_accuracy`` is the fraction of samples whose recognised fault set equals the true
    one.  ``tdr``, ``far`` and ``fia`` are the standard per-sample FDI rates of
    :mod:`uimm_jax.engine.metrics` (:func:`run_fdi_counts`).  With ``chunk_timings``
    (``(steps, seconds)`` per chunk), ``steps_per_s`` is the
    steady-state rate of the chunks after the first and ``compile_s`` estimates the
    compilation time (first chunk minus its steady-state share).  ``est_settings``: every
    ``EstSettings`` field of a ``uimm-est`` run (``[filter.est]``), ``None`` for the others.
    ``innovation_check`` (:func:`~uimm_jax.engine.metrics.innovation_check`): the mean of
    the leading model's NIS per channel against its expected 1, and whether the filter's
    noise fits the data, also per measured output (``None`` without the ``nis`` output).
    """
    sc, diag = setup.scenario, setup.diagnoser
    names = list(setup.table.names)
    dt = float(sc.dt)
    N = int(truth_codes.shape[0])
    F = len(names)
    onset = metrics.first_steps(truth_codes, F)
    decl_step = metrics.first_steps(outputs["declared"], F)
    false_mask = metrics.false_declared(onset, decl_step)
    found = metrics.detected(onset, decl_step)
    decl = metrics.declaration_list(decl_step, names, dt)
    is_false = [bool(false_mask[names.index(d["fault"])]) for d in decl]
    hold = int(sc.filter.decision.hold)
    if isinstance(diag, UIMMEstDiagnoser) and diag.per_sample.retract_hold:
        hold = int(diag.per_sample.retract_hold)  # the samples its retraction rule counts
    changes = decision_changes(outputs, truth_codes, names, dt, hold)
    if "declarations" in changes:  # a diagnoser that retracts: every switch on counts
        decl = changes["declarations"]
        is_false = [not d["correct"] for d in decl]
    false = [
        {"fault": d["fault"], "time": d["time"]} for d, f in zip(decl, is_false, strict=True) if f
    ]
    delays = {}
    for ev, k_ev in zip(sc.events, setup.event_steps, strict=True):
        j = names.index(ev.fault)
        delays[ev.fault] = metrics.sample_time(decl_step[j] - k_ev, dt) if found[j] else None
    correct = np.sum(np.asarray(outputs["recognised"]) == truth_codes)
    health = metrics.health_counts(outputs["health"])
    fdi = metrics.fdi_rates(run_fdi_counts(setup, truth_codes, outputs), N)
    nis = [outputs[k] if k in outputs else None for k in ("nis", "nis_channels")]
    ic = None if nis[0] is None else metrics.innovation_check(*nis, sc.plant.output_names, dt)
    return {
        "scenario": sc.name,
        "source": sc.source,
        "method": setup.method,
        "seed": seed,
        "num_models": setup.diagnoser.num_models,
        "num_faults": len(names),
        "num_steps": N,
        "dt": dt,
        "duration_s": N * dt,
        "faults": names,
        "events": [
            {"fault": ev.fault, "time": float(ev.time), "magnitude": float(ev.magnitude)}
            | {"ramp": float(ev.ramp), "end": None if ev.end is None else float(ev.end)}
            | {"growth": ev.growth}
            for ev in sc.events
        ],
        "declarations": [
            {"fault": d["fault"], "time": d["time"], "correct": not f}
            | {k: d[k] for k in ("magnitude", "magnitude_ci") if k in d}
            for d, f in zip(decl, is_false, strict=True)
        ],
        "retractions": changes["retractions"],
        "detection_delay_s": delays,
        "false_declarations": len(false),
        "false_declaration_list": false,
        "mode_accuracy": metrics.mode_accuracy(correct, N),
        **fdi,
        "innovation_check": ic,
        "transition": setup.transition.tolist(),
        "initial_mode_probs": setup.initial_mode_probs.tolist(),
        "threshold": float(sc.filter.decision.threshold),
        "hold": int(sc.filter.decision.hold),
        "est_settings": diag.settings._asdict() if isinstance(diag, UIMMEstDiagnoser) else None,
        "health": {f"{name}_steps": count for name, count in health.items()},
        "runtime_s": float(runtime_s),
        "simulation_runtime_s": None if sim_runtime_s is None else float(sim_runtime_s),
        **_rates(N, runtime_s, chunk_timings),
        "dtype": str(setup.params.imm.Q.dtype),
    }
