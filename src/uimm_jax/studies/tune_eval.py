"""Evaluation of tuned settings with the exact hard rule, and the tuned scenario file.

:func:`hard_metrics` reads the hard declarations of a training forward pass;
:func:`evaluate` and :func:`before_after` run :func:`uimm_jax.studies.sweep.run_sweep` on
held-out seeds; :func:`tuned_scenario` writes the tuned ``[filter]`` settings.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from uimm_jax.engine import metrics
from uimm_jax.engine.truth import NEVER
from uimm_jax.scenario.parse import parse_scenario
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.studies.sweep import run_sweep
from uimm_jax.studies.tune_loss import Problem, TrainingBatch

__all__ = [
    "before_after",
    "before_after_table",
    "evaluate",
    "hard_metrics",
    "rescale_scenario",
    "tuned_scenario",
]


def hard_metrics(problem: Problem, batch: TrainingBatch, decl_step: np.ndarray) -> dict:
    """Detection, isolation and false declarations of a batch from hard declaration steps.

    A declaration of ``j`` is correct when ``j`` is present in the truth at that step
    (as in :func:`uimm_jax.studies.run.summarize`).

    Args:
        problem: the :class:`Problem`.
        batch: the :class:`TrainingBatch`.
        decl_step: ``(B, F)`` declaration steps (``LossParts.decl_step``).

    Returns:
        dict with ``detection_rate``, ``false_runs`` (runs with a false declaration),
        ``median_delay_s`` per fault and ``runs``.
    """
    on = np.asarray(batch.onset).astype(np.int64)
    on = np.where(on == NEVER, -1, on)
    de = np.asarray(decl_step).astype(np.int64)
    has = on >= 0
    det = metrics.detected(on, de)
    false = metrics.false_declared(on, de)
    names = problem.diagnoser.table.names
    delays = {}
    for j, f in enumerate(names):
        d = (de[det[:, j], j] - on[det[:, j], j]) * problem.dt
        if has[:, j].any():
            delays[f] = metrics.delay_stats(d)["median"]
    return {
        "runs": int(on.shape[0]),
        "events": int(has.sum()),
        "detection_rate": float(det.sum() / max(has.sum(), 1)),
        "false_runs": int(np.any(false, axis=1).sum()),
        "median_delay_s": delays,
    }


def rescale_scenario(scenario, duration: float):
    """The scenario with another duration, its event times scaled by the same factor.

    Args:
        scenario: a :class:`~uimm_jax.scenario.spec.Scenario`.
        duration: the new duration in s (a whole number of samples).

    Returns:
        A validated :class:`~uimm_jax.scenario.spec.Scenario` (the same object if unchanged).
    """
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

    Runs :func:`uimm_jax.studies.sweep.run_sweep` on the scenario's events, the events of
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
        b = evaluate(
            before_scenario,
            runs=runs,
            seed=seed,
            progress="before" if progress is True else progress,
            cases_from=cases,
        )
    a = evaluate(
        after_scenario,
        runs=runs,
        seed=seed,
        progress="after" if progress is True else progress,
        cases_from=cases,
    )
    return before_after_table(b, a), {"before": b, "after": a, "seed": seed, "runs": runs}


def tuned_scenario(scenario, settings: Mapping[str, Any], *, name: str | None = None) -> dict:
    """The scenario's dict (:func:`~uimm_jax.scenario.write.scenario_to_dict`) with tuned settings.

    The transition matrix is written in full (``[filter].transition``, rows renormalised
    in float64 so that they sum to 1 within the file's tolerance), with the threshold and
    the integer hold in ``[filter.decision]``.  Noise scales are not written (the
    scenario's ``[noise]`` is also the truth's).

    Args:
        scenario: the source scenario.
        settings: :func:`settings_from_params` output.
        name: the new scenario name (default: ``<name>-gd``, for gradient descent -- not
            ``-tuned``, the suffix of the shipped hand-tuned files -- or the name unchanged
            if it already ends in ``-gd``, so that tuning a tuned file again does not stack
            suffixes).

    Returns:
        A dict for :func:`~uimm_jax.scenario.parse.parse_scenario` / ``dump_scenario``.
    """
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
    default = scenario.name if scenario.name.endswith("-gd") else f"{scenario.name}-gd"
    d["name"] = name or default
    return d
