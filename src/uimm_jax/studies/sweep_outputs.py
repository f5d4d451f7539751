"""The results of a sweep: per-run arrays, per-cell metrics, ``results.json/csv``, figures.

:class:`SweepResult` holds what :func:`uimm_jax.studies.sweep.run_sweep` measured, as
arrays per cell and run; :func:`cell_summary` turns one cell into its metrics (the
definitions live in :mod:`uimm_jax.engine.metrics`) and :func:`write_sweep_outputs`
writes them.

**Metrics** (per cell, :func:`cell_summary`; a declaration of fault ``j`` at step ``k`` is
*correct* when ``j`` is present in the truth at ``k``, as in
:func:`uimm_jax.studies.run.summarize`):

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
* ``tdr``, ``far``, ``fia``: the standard per-sample FDI rates (true detection rate,
  false alarm rate, fault isolation accuracy) pooled over the cell's samples, as defined
  in :mod:`uimm_jax.engine.metrics`;
* ``state_rmse``: root mean square of the combined estimate's error, per state;
* ``runs_unexplained``: runs with an unexplained spell, where the innovations are far
  too large for the bank and its noise for at least 0.3 s
  (:mod:`uimm_jax.engine.innovation`: a fault the bank does not hold, a wrong noise);
* ``mean_nis_by_output``: per measured output, the same model's ``e_i^2 / S_ii`` averaged
  over the cell's samples (1 when that output's noise fits; the run's ``by_channel``);
* ``mean_nis_per_channel``: the most probable model's normalised innovation squared per
  channel, averaged over the cell's samples: 1 when the filter's noise is the truth's
  (the innovation check of a run, :func:`uimm_jax.engine.metrics.innovation_check`;
  ``noise_scales`` other than 1 move it).
"""

from __future__ import annotations

import csv
import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from uimm_jax.engine import metrics
from uimm_jax.scenario.sweep import FAULT_FREE, SweepSpec
from uimm_jax.studies.exports import write_runs_csv

__all__ = ["Cell", "SweepResult", "cell_summary", "spec_settings", "write_sweep_outputs"]

_RUN_HEALTH = ("cov_repaired", "nonfinite_caught", "gated")  # simulated runs miss nothing


class Cell(NamedTuple):
    """One cell of a sweep.

    Attributes:
        index: position in :attr:`SweepResult.cells`.
        method: ``"uimm"`` or ``"imm"``.
        case: the case name (``"fault-free"`` for the fault-free case).
        magnitude: the magnitude scale (0 for the fault-free case).
        noise_scale: the truth noise scale.
        ramp: s, the ramp of every event of the cell (``None``: the events' own).
    """

    index: int
    method: str
    case: str
    magnitude: float
    noise_scale: float
    ramp: float | None = None


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
        fdi: :class:`~uimm_jax.engine.metrics.FDICounts` of ``(C, R)`` arrays (TDR, FAR,
            FIA), or ``None``.
        unexplained: ``(C, R)`` the first step of each run's first unexplained spell (-1:
            none), or ``None``.
        nis_channels: ``(C, R, m)`` each run's summed per-output NIS of the leading model,
            or ``None``; ``outputs``: the ``m`` output names.
        nis: ``(C, R)`` each run's summed NIS per channel of the leading model (its mean
            over the run: ``/ num_steps``; the innovation check), or ``None``.
        noise_keys: ``(R, 2)`` uint32 noise key of each run, or ``None``.
        true_magnitude: ``(C, R, F)`` the truth's magnitude of each fault at the run's
            last step (a ramp's level if it has not completed; an ended fault's as if it
            had stayed; 0: no event).
        end_step: ``(C, R, F)`` step at which each fault ends (-1: never).
        estimates: for size-estimating methods (``uimm-est``), ``(C, R, ...)`` arrays
            ``retract_step``, ``declarations``, ``false_count``, ``magnitude`` and
            ``magnitude_sd`` (NaN for the other methods' cells); else ``None``.
        summaries: one dict per cell (:func:`cell_summary`).
        runtime_s: wall time of the simulations (compilation included).
        devices: number of devices the run axis was sharded over (all processes).
        processes: number of processes (``jax.process_count()``).
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
    fdi: metrics.FDICounts | None = None
    nis: np.ndarray | None = None
    unexplained: np.ndarray | None = None
    nis_channels: np.ndarray | None = None
    outputs: tuple[str, ...] = ()
    noise_keys: np.ndarray | None = None
    true_magnitude: np.ndarray | None = None
    end_step: np.ndarray | None = None
    estimates: dict | None = None
    summaries: list[dict] = dataclasses.field(default_factory=list)
    runtime_s: float = 0.0
    devices: int = 1
    processes: int = 1
    batch: int = 0
    chunk: int = 0

    @property
    def run_steps(self) -> int:
        """Total number of simulated run-steps."""
        return len(self.cells) * self.spec.runs * self.num_steps

    def run_arrays(self) -> dict[str, np.ndarray]:
        """The per-run arrays by name (what ``runs.npz`` holds)."""
        return {
            "onset_step": self.onset_step,
            "decl_step": self.decl_step,
            "correct_samples": self.correct_samples,
            "sq_err": self.sq_err,
            "health": self.health,
            **{f"fdi_{k}": v for k, v in self.fdi._asdict().items()},
            **({} if self.nis is None else {"nis_sum": self.nis}),
            **({} if self.unexplained is None else {"unexplained_step": self.unexplained}),
            **({} if self.nis_channels is None else {"nis_by_output_sum": self.nis_channels}),
        }

    def detected(self) -> np.ndarray:
        """``(C, R, F)`` bool: the fault occurred and was correctly declared."""
        return metrics.detected(self.onset_step, self.decl_step)

    def isolated(self) -> np.ndarray:
        """``(C, R)`` bool: every fault event of the run isolated (confusion diagonal)."""
        return metrics.isolated(self.onset_step, self.decl_step, self.num_steps)

    def false_declared(self) -> np.ndarray:
        """``(C, R, F)`` bool: the fault was declared while absent from the truth."""
        return metrics.false_declared(self.onset_step, self.decl_step)

    def to_json(self) -> dict:
        """The ``results.json`` document."""
        return {
            "scenario": self.scenario,
            "source": self.source,
            "faults": list(self.faults),
            "states": list(self.states),
            "dt": self.dt,
            "num_steps": self.num_steps,
            "duration_s": self.num_steps * self.dt,
            **spec_settings(self.spec),
            "batch": self.batch,
            "chunk": self.chunk,
            "devices": self.devices,
            "processes": self.processes,
            "run_steps": self.run_steps,
            "runtime_s": self.runtime_s,
            "run_steps_per_s": self.run_steps / self.runtime_s if self.runtime_s > 0 else None,
            "cells": self.summaries,
        }


def spec_settings(spec: SweepSpec) -> dict:
    """The settings of a sweep that decide its numbers, as JSON values.

    ``seed``, ``runs``, ``methods``, ``magnitudes``, ``noise_scales``, ``cases`` and
    ``fault_free``; not ``batch`` nor ``chunk``, which change the speed and never the
    numbers.  Shared by ``results.json`` and the resume record
    (:mod:`uimm_jax.studies.sweep_store`).
    """
    return {
        "seed": spec.seed,
        "runs": spec.runs,
        "methods": list(spec.methods),
        "magnitudes": list(spec.magnitudes),
        "noise_scales": list(spec.noise_scales),
        "cases": [
            {
                "name": c.name,
                "events": [
                    {
                        "fault": e.fault,
                        "time": list(e.time),
                        "magnitude": e.magnitude,
                        "ramp": e.ramp,
                        "duration": None if e.duration is None else list(e.duration),
                        "growth": e.growth,
                    }
                    for e in c.events
                ],
            }
            for c in spec.cases
        ],
        "fault_free": spec.fault_free,
        "ramps": list(spec.ramps),
    }


def estimate_summary(result: SweepResult, index: int) -> dict:
    """Size and retraction metrics of a cell of a size-estimating method (else ``{}``).

    * ``magnitude_bias`` and ``magnitude_mare`` (median absolute relative error) of the
      estimate at the end of the run, and ``magnitude_coverage``, the share of runs whose
      95 % interval holds the truth -- over the runs where the fault is present at the end
      and declared;
    * ``retraction_probability`` and ``retraction_delay_s`` (median, p95) over the runs
      whose fault ended: retracted after its end, and how long after;
    * ``false_declarations_all``: every declaration of an absent fault, re-declarations
      included (``false_declarations`` counts first declarations);
    * ``wrong_retractions``: runs whose last retraction of a fault came while it was
      present (after its onset, before its end).
    """
    est = result.estimates
    if est is None or np.all(np.isnan(est["magnitude"][index])):
        return {}
    on, end = result.onset_step[index], result.end_step[index]
    truth = result.true_magnitude[index]
    mag, sd = est["magnitude"][index], est["magnitude_sd"][index]
    ret = est["retract_step"][index]
    bias, mare, cov, rp, rd, wrong = {}, {}, {}, {}, {}, {}
    for j, f in enumerate(result.faults):
        present = (
            (on[:, j] >= 0) & (ret[:, j] >= on[:, j]) & ((end[:, j] < 0) | (ret[:, j] < end[:, j]))
        )
        if (on[:, j] >= 0).any():
            wrong[f] = int(np.sum(present))
        stays = (on[:, j] >= 0) & (end[:, j] < 0) & (result.decl_step[index][:, j] >= 0)
        stays &= ret[:, j] < 0
        if stays.any():
            err = mag[stays, j] - truth[stays, j]
            bias[f] = float(np.mean(err))
            mare[f] = float(np.median(np.abs(err) / truth[stays, j]))
            cov[f] = float(np.mean(np.abs(err) <= 1.959963984540054 * sd[stays, j]))
        ends = (on[:, j] >= 0) & (end[:, j] >= 0)
        if ends.any():
            ok = ends & (ret[:, j] >= end[:, j])
            rp[f] = float(ok.sum() / ends.sum())
            d = metrics.delay_stats((ret[ok, j] - end[ok, j]).astype(np.float64) * result.dt)
            rd[f] = {"median": d["median"], "p95": d["p95"], "max": d["max"]}
    return {
        "magnitude_bias": bias,
        "magnitude_mare": mare,
        "magnitude_coverage": cov,
        "retraction_probability": rp,
        "retraction_delay_s": rd,
        "false_declarations_all": int(est["false_count"][index].sum()),
        "wrong_retractions": wrong,
    }


def cell_summary(result: SweepResult, index: int) -> dict:
    """The metrics of one cell (a ``results.json`` cell; see the module doc)."""
    cell = result.cells[index]
    dt = result.dt
    N = result.num_steps
    on = result.onset_step[index]
    de = result.decl_step[index]
    R = on.shape[0]
    faults = result.faults
    det = metrics.detected(on, de)
    false = metrics.false_declared(on, de)
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
        ci[f] = list(metrics.wilson_interval(k, n))
        d = metrics.delay_stats((de[det[:, j], j] - on[det[:, j], j]).astype(np.float64) * dt)
        mean_d[f], med_d[f], p95_d[f], max_d[f] = d["mean"], d["median"], d["p95"], d["max"]
    first_onset = np.where(on >= 0, on, N).min(axis=1)  # (R,)
    ff_steps = int(first_onset.sum())
    ff_hours = ff_steps * dt / 3600.0
    ff_false = int(np.sum((de >= 0) & (de < first_onset[:, None])))
    conf = metrics.confusion(on, de, N)
    n_events = int(conf[1:].sum())
    iso_k = int(np.trace(conf[1:, :-1]))
    runs_false = int(np.any(false, axis=1).sum())
    sq = result.sq_err[index]  # (R, n)
    rmse = np.sqrt(sq.sum(axis=0) / (R * N))
    health = metrics.health_counts(result.health[index])
    fdi = {"tdr": None, "far": None, "fia": None}
    if result.fdi is not None:
        fdi = metrics.fdi_rates(metrics.FDICounts(*(a[index] for a in result.fdi)), R * N)
    return {
        "method": cell.method,
        "case": cell.case,
        "magnitude": cell.magnitude,
        "ramp": cell.ramp,
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
        "false_declaration_run_probability_ci": list(metrics.wilson_interval(runs_false, R)),
        "false_declarations_fault_free": ff_false,
        "fault_free_hours": ff_hours,
        "false_alarm_rate_per_hour": ff_false / ff_hours if ff_hours > 0 else None,
        "isolation_accuracy": iso_k / n_events if n_events else None,
        "isolation_accuracy_ci": (
            list(metrics.wilson_interval(iso_k, n_events)) if n_events else None
        ),
        "confusion": {
            "rows": ["fault-free"] + list(faults),
            "columns": list(faults) + ["none"],
            "matrix": conf.tolist(),
        },
        "mode_accuracy": metrics.mode_accuracy(result.correct_samples[index], R * N),
        "mode_accuracy_min_run": metrics.mode_accuracy(result.correct_samples[index].min(), N),
        **fdi,
        "mean_nis_per_channel": None
        if result.nis is None
        else float(result.nis[index].sum() / (R * N)),
        "mean_nis_by_output": None
        if result.nis_channels is None
        else {
            o: float(result.nis_channels[index, :, i].sum() / (R * N))
            for i, o in enumerate(result.outputs)
        },
        "runs_unexplained": None
        if result.unexplained is None
        else int(np.sum(result.unexplained[index] >= 0)),
        "state_rmse": {s: float(v) for s, v in zip(result.states, rmse, strict=True)},
        "health": {f"runs_{name}": health[name] for name in _RUN_HEALTH},
        **estimate_summary(result, index),
    }


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
        "tdr",
        "far",
        "fia",
        "mean_nis_per_channel",
        "runs_unexplained",
    ]
    head += [f"nis:{o}" for o in result.outputs] + [f"rmse:{s}" for s in result.states]
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
            s["tdr"],
            s["far"],
            s["fia"],
            s.get("mean_nis_per_channel"),
            s.get("runs_unexplained"),
        ]
        by = s.get("mean_nis_by_output") or {}
        row += [by.get(o) for o in result.outputs] + [s["state_rmse"][st] for st in result.states]
        rows.append(["" if v is None else v for v in row])
    return head, rows


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


def write_sweep_outputs(
    result: SweepResult, out: str | Path, *, figures: bool = True, extra: Mapping | None = None
) -> list[Path]:
    """Write ``results.json``, ``results.csv``, ``runs.csv``, ``runs.npz`` and the figures.

    ``runs.npz`` holds the per-run arrays (:meth:`SweepResult.run_arrays`).

    ``runs.csv`` has one row per run (:func:`uimm_jax.studies.exports.run_rows`).

    Figures: ``sweep_<case>.png`` for each fault case (detection probability and median
    delay per fault, isolation accuracy, false declarations per run, mode accuracy and
    TDR / FAR / FIA against magnitude, every method on the same axes, the fault-free
    cells as reference lines; see :func:`~uimm_jax.studies.plots_sweep.plot_sweep`), and
    ``confusion_<method>.png`` (one confusion matrix per magnitude, summed over the
    method's cells of that magnitude, coloured by the share of each row).

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
    written = [out / "results.json", out / "results.csv", out / "runs.npz"]
    written[0].write_text(json.dumps(doc, indent=2) + "\n")
    np.savez(written[2], **result.run_arrays())
    head, rows = _csv_rows(result)
    with written[1].open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        w.writerows(rows)
    written.append(write_runs_csv(result, out / "runs.csv"))
    if not figures:
        return written
    from uimm_jax.studies import plots, plots_sweep

    for case in result.spec.cases:
        cells = [s for s in result.summaries if s["case"] == case.name]
        fig = plots_sweep.plot_sweep(
            cells,
            fault_free=[s for s in result.summaries if s["case"] == FAULT_FREE],
            title=f"{result.scenario}: case {case.name!r}, {result.spec.runs} runs per cell "
            "(95 % Wilson intervals)",
        )
        written.append(plots.save_figure(fig, out / f"sweep_{_safe(case.name)}.png"))
    for method in result.spec.methods:
        ss = [s for s in result.summaries if s["method"] == method]
        panels = []
        for mag in sorted({s["magnitude"] for s in ss}):
            group = [s for s in ss if s["magnitude"] == mag]
            mat = np.sum([s["confusion"]["matrix"] for s in group], axis=0)
            name = "fault-free runs" if mag == 0 else f"magnitude {mag:g}"
            panels.append((f"{name} ({len(group)} cell{'s' * (len(group) > 1)})", mat))
        conf = ss[0]["confusion"]
        fig = plots_sweep.plot_confusion_grid(
            panels,
            conf["rows"],
            conf["columns"],
            title=f"{method.upper()}: first new declaration per event, by magnitude "
            "(colour: share of the row)",
        )
        written.append(plots.save_figure(fig, out / f"confusion_{method}.png"))
    return written
