"""What a researcher keeps: per-step exports of a run and per-run exports of a sweep.

* :func:`timeseries_arrays` and :func:`write_timeseries`: ``timeseries.npz`` of a
  ``uimm-jax run`` (every sample), :func:`write_timeseries_csv` a decimated CSV of it.
* :func:`run_rows` and :func:`write_runs_csv`: ``runs.csv`` of a ``uimm-jax sweep``, one row
  per run (cell, run index, seed, noise key, onsets, declarations marked correct or false,
  mode accuracy and the FDI rates of the run).

The definitions of "correct", "false", TDR, FAR and FIA are those of
:mod:`uimm_jax.engine.metrics`.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from uimm_jax.engine import metrics

__all__ = [
    "TIMESERIES_KEYS",
    "TIMESERIES_OPTIONAL_KEYS",
    "run_rows",
    "timeseries_arrays",
    "write_runs_csv",
    "write_timeseries",
    "write_timeseries_csv",
]

TIMESERIES_KEYS = ("time", "mode_probs", "recognised", "declared", "mean", "health")
"""Arrays of every ``timeseries.npz`` (see :func:`timeseries_arrays`)."""

TIMESERIES_OPTIONAL_KEYS = ("magnitude", "magnitude_sd", "nis", "nis_channels")
"""Per-step outputs that some runs record, exported under the same name when a run's
``outputs`` holds them: a size-estimating diagnoser's (``uimm-est``) fault-size estimate
``magnitude`` ``(N, F)`` and its standard deviation ``magnitude_sd`` ``(N, F)``, per fault
(model 0's for a declared fault, its hypothesis' own for an undeclared one; the 95 %
interval is ``magnitude +- 1.96 magnitude_sd``, as in ``summary.json``); and ``nis``
``(N,)``, the most probable model's normalised innovation squared per observed channel
(mean 1 when the filter's noise is the data's; NaN where nothing was observed;
:func:`uimm_jax.engine.scan.leading_nis`), and ``nis_channels`` ``(N, m)``, the same
model's ``e_i^2 / S_ii`` on each measured output (``outputs`` order; NaN where missing;
:func:`uimm_jax.engine.scan.leading_nis_channels`)."""


def timeseries_arrays(result) -> dict[str, np.ndarray]:
    """The per-step arrays of a run, as written to ``timeseries.npz``.

    Args:
        result: a :class:`~uimm_jax.studies.run.RunResult`.

    Returns:
        ``time`` (N,) sample times in s; ``mode_probs`` (N, M) mode probabilities (model
        order of ``model_labels``); ``recognised`` (N,) and ``declared`` (N,) fault-set
        codes (bit j = fault j of ``faults``); ``mean`` (N, n) combined state estimate
        (eq. 30); ``health`` (N,) health bits (``health_flags``); ``truth`` (N,) the true
        fault-set code (the scenario's events for measured data); the names
        ``model_labels``, ``faults``, ``states``, ``outputs`` (the measured outputs) and
        ``health_flags`` (bit values) as arrays; and each key of
        :data:`TIMESERIES_OPTIONAL_KEYS` the run recorded (``uimm-est``: ``magnitude`` and
        ``magnitude_sd``, ``(N, F)``; every run of
        :func:`~uimm_jax.studies.run.filter_measurements`: ``nis`` ``(N,)`` and
        ``nis_channels`` ``(N, m)``).
    """
    o = result.outputs
    setup = result.setup
    arrays = {
        "time": np.asarray(result.truth["t"]),
        "mode_probs": np.asarray(o["mode_probs"]),
        "recognised": np.asarray(o["recognised"]),
        "declared": np.asarray(o["declared"]),
        "mean": np.asarray(o["mean"]),
        "health": np.asarray(o["health"]),
        "truth": np.asarray(result.truth["truth"]),
        "model_labels": np.array(setup.diagnoser.model_labels()),
        "faults": np.array(list(setup.table.names)),
        "states": np.array(list(setup.scenario.plant.state_names)),
        "outputs": np.array(list(setup.scenario.plant.output_names)),
        "health_flags": np.array([f"{name}={bit}" for name, bit in metrics.HEALTH_FLAGS.items()]),
    }
    for key in TIMESERIES_OPTIONAL_KEYS:
        if key in o:
            arrays[key] = np.asarray(o[key])
    return arrays


def write_timeseries(result, path: str | Path) -> Path:
    """Write :func:`timeseries_arrays` to ``path`` (``.npz``, compressed)."""
    path = Path(path)
    np.savez_compressed(path, **timeseries_arrays(result))
    return path


def decimation_steps(declared, recognised, every: int) -> np.ndarray:
    """Samples kept by the CSV: every ``every``-th one, plus each change of a fault set.

    Sample 0, the last sample and every sample at which the declared or the recognised
    set differs from the sample before are always kept, so no transition is lost.
    """
    declared, recognised = np.asarray(declared), np.asarray(recognised)
    N = declared.shape[0]
    keep = np.zeros(N, bool)
    keep[::every] = True
    if N:
        keep[-1] = True
        keep[1:] |= (declared[1:] != declared[:-1]) | (recognised[1:] != recognised[:-1])
    return np.flatnonzero(keep)


def write_timeseries_csv(result, path: str | Path, *, every: int | None = None) -> Path:
    """Write a decimated CSV of :func:`timeseries_arrays` to ``path``.

    Columns: ``step``, ``time``, ``mode_prob:<model>`` per model, ``recognised`` and
    ``declared`` (codes), ``recognised_set`` and ``declared_set`` (fault names joined by
    ``+``), ``truth``, ``mean:<state>`` per state, ``health``, then the optional arrays.

    Args:
        result: a :class:`~uimm_jax.studies.run.RunResult`.
        path: the CSV file.
        every: keep every ``every``-th sample (plus the changes, see
            :func:`decimation_steps`); default: about 10,000 rows.
    """
    a = timeseries_arrays(result)
    N = a["time"].shape[0]
    every = max(1, N // 10_000) if every is None else int(every)
    rows = decimation_steps(a["declared"], a["recognised"], every)
    faults = [str(f) for f in a["faults"]]
    names = lambda code: "+".join(f for j, f in enumerate(faults) if code >> j & 1)  # noqa: E731
    head = ["step", "time"]
    head += [f"mode_prob:{m}" for m in a["model_labels"]]
    head += ["recognised", "declared", "recognised_set", "declared_set", "truth"]
    head += [f"mean:{s}" for s in a["states"]] + ["health"]
    extra = [k for k in TIMESERIES_OPTIONAL_KEYS if k in a]
    for k in extra:
        width = a[k].reshape(N, -1).shape[1]
        if a[k].ndim == 1:  # one value a step
            head += [k]
        elif k == "nis_channels":  # one value a measured output
            head += [f"nis:{o}" for o in a["outputs"]]
        elif width == len(faults):
            head += [f"{k}:{f}" for f in faults]
        else:
            head += [f"{k}:{i}" for i in range(width)]
    path = Path(path)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for k in rows:
            rec, dec = int(a["recognised"][k]), int(a["declared"][k])
            row = [int(k), repr(float(a["time"][k]))]
            row += [f"{v:.9g}" for v in a["mode_probs"][k]]
            row += [rec, dec, names(rec), names(dec), int(a["truth"][k])]
            row += [f"{v:.12g}" for v in a["mean"][k]] + [int(a["health"][k])]
            for key in extra:
                row += [f"{v:.12g}" for v in a[key].reshape(N, -1)[k]]
            w.writerow(row)
    return path


def run_rows(result) -> tuple[list[str], list[list]]:
    """Header and rows of ``runs.csv``: one row per run of a sweep.

    Columns: ``cell``, ``method``, ``case``, ``magnitude``, ``noise_scale``, ``run`` (the
    run index ``r``: run ``r`` of every cell shares its noise), ``seed`` (the sweep's root
    seed), ``noise_key`` (the run's truth-noise key, two uint32 words in hex), then per
    fault ``<fault>:onset_s`` (the event time, ``onset step * dt``; empty: no event),
    ``<fault>:declared_s`` (the declaring sample's time, ``(step + 1) * dt``; empty: never
    declared) and ``<fault>:declaration`` (``correct``, ``false`` or empty), then
    ``mode_accuracy``, ``tdr``, ``far``, ``fia``, ``nis`` (the mean over the run of the
    most probable model's NIS per channel, 1 when the filter's noise fits) and
    ``unexplained_s`` (the start of the run's first unexplained spell, ``(step + 1) * dt``;
    empty: none; :mod:`uimm_jax.engine.innovation`) of the run.  A
    sweep with a size-estimating method (``uimm-est``) adds per fault, after
    ``<fault>:declaration``, ``<fault>:retracted_s`` (the time of its last retraction,
    ``(step + 1) * dt``; empty: never retracted), ``<fault>:magnitude`` and
    ``<fault>:magnitude_sd`` (the estimate and its standard deviation at the last sample;
    empty in another method's cells).

    Args:
        result: a :class:`~uimm_jax.studies.sweep_outputs.SweepResult`.
    """
    faults = result.faults
    dt, N = result.dt, result.num_steps
    head = ["cell", "method", "case", "magnitude", "noise_scale", "run", "seed", "noise_key"]
    est = result.estimates
    for f in faults:
        head += [f"{f}:onset_s", f"{f}:declared_s", f"{f}:declaration"]
        if est is not None:
            head += [f"{f}:retracted_s", f"{f}:magnitude", f"{f}:magnitude_sd"]
    head += ["mode_accuracy", "tdr", "far", "fia", "nis", "unexplained_s"]
    false = metrics.false_declared(result.onset_step, result.decl_step)  # (C, R, F)
    rows = []
    for cell in result.cells:
        c = cell.index
        for r in range(result.onset_step.shape[1]):
            key = "" if result.noise_keys is None else _key_hex(result.noise_keys[r])
            row = [c, cell.method, cell.case, cell.magnitude, cell.noise_scale, r]
            row += [result.spec.seed, key]
            for j in range(len(faults)):
                on, de = int(result.onset_step[c, r, j]), int(result.decl_step[c, r, j])
                row += [
                    metrics.sample_time(on, dt) if on >= 0 else "",
                    metrics.sample_time(de + 1, dt) if de >= 0 else "",
                    ("false" if false[c, r, j] else "correct") if de >= 0 else "",
                ]
                if est is not None:
                    row += _est_cells(est, c, r, j, dt)
            row.append(metrics.mode_accuracy(result.correct_samples[c, r], N))
            rates = {"tdr": "", "far": "", "fia": ""}
            if result.fdi is not None:
                counts = metrics.FDICounts(*(a[c, r] for a in result.fdi))
                rates = metrics.fdi_rates(counts, N)
            row += ["" if v is None else v for v in rates.values()]
            row.append("" if result.nis is None else float(result.nis[c, r]) / N)
            u = -1 if result.unexplained is None else int(result.unexplained[c, r])
            row.append("" if u < 0 else metrics.sample_time(u + 1, result.dt))
            rows.append(row)
    return head, rows


def _est_cells(est: dict, c: int, r: int, j: int, dt: float) -> list:
    """Columns ``retracted_s``, ``magnitude``, ``magnitude_sd`` of fault j, run r, cell c."""
    ret = int(est["retract_step"][c, r, j])
    m, sd = float(est["magnitude"][c, r, j]), float(est["magnitude_sd"][c, r, j])
    size = ["", ""] if np.isnan(m) else [m, sd]  # NaN: a cell of another method
    return [metrics.sample_time(ret + 1, dt) if ret >= 0 else "", *size]


def _key_hex(key) -> str:
    """A raw ``(2,)`` uint32 PRNG key as 16 hex digits."""
    return "".join(f"{int(w):08x}" for w in key)


def write_runs_csv(result, path: str | Path) -> Path:
    """Write :func:`run_rows` to ``path``."""
    path = Path(path)
    head, rows = run_rows(result)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        w.writerows(rows)
    return path
