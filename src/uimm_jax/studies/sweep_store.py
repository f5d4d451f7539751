"""Resumable sweeps: each finished batch's per-run arrays on disk, written atomically.

A sweep given a checkpoint folder (``uimm-jax sweep --out DIR`` uses ``DIR/checkpoint``)
writes there, before it starts, ``manifest.json``: the scenario (as
:func:`~uimm_jax.scenario.write.scenario_to_dict` writes it, without its ``[sweep]``
table) and the settings that decide the numbers
(:func:`~uimm_jax.studies.sweep_outputs.spec_settings` and the float dtype).  After each
batch it writes ``batch-NNNNN.npz``: the cell and run index of each of the batch's runs
and their per-run arrays (declaration steps, samples with the right mode, summed squared
errors, health flags, FDI counts and, for every method, the size-estimating method's
arrays: retraction steps, declaration counts, false declarations, magnitude estimates;
their "none" values for the other methods' runs).  Every file is written to a temporary
name in the same folder, flushed to disk and renamed (``os.replace``, atomic on POSIX),
so a kill at any moment leaves only whole files; leftover temporary files are removed
when the folder is opened again.

The manifest also records the batch layout: the runs per batch and the number of devices
(over all processes).  Resuming (``resume=True``) reads the manifest, refuses when the
scenario, the settings or the layout differ (naming each differing field), and loads the
finished runs; the sweep then runs only the others, in the same batches as an
uninterrupted sweep (the batches run in order and are stored whole), so a resumed sweep
equals an uninterrupted one bit for bit.  The chunk length and the process count may
change (one process with two devices and two processes with one each give the same
bits).  The layout is kept anyway, the cautious choice: the covariance update chose its
form once per device batch until session 5, when batch layouts differed in the last bits
of the state errors; it now chooses per filter (docs/montecarlo.md).  A sweep that is
not resumed refuses a folder that holds an unfinished sweep (it would discard finished
batches), and starts afresh over a finished one.

In a multi-process sweep process 0 reads and writes the folder and shares what it read
with the others (:func:`uimm_jax.studies.distributed.share`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from uimm_jax.engine.uimm_est import UIMMEstDiagnoser
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.studies.distributed import is_main, share
from uimm_jax.studies.sweep_outputs import spec_settings

__all__ = ["Finished", "SweepStore", "open_store"]

FORMAT = "uimm-jax sweep checkpoint 3"
MANIFEST = "manifest.json"
_FIELDS = (
    "decl_step",
    "correct",
    "sq_err",
    "health",
    "fdi_faulty",
    "fdi_flagged_faulty",
    "fdi_flagged_free",
    "fdi_true_prob",
    "nis",
    "unexplained",
    "nis_channels",
)
_EST_FIELDS = (
    "est_retract_step",
    "est_declarations",
    "est_false_count",
    "est_magnitude",
    "est_magnitude_sd",
)
"""The arrays of a size-estimating method (``uimm-est``), ``SweepResult.estimates``."""


class Finished(NamedTuple):
    """The runs a checkpoint already holds, as ``(C, R, ...)`` arrays.

    Attributes:
        done: ``(C, R)`` uint8, 1 where the run is finished.
        decl_step: ``(C, R, F)`` declaration steps.
        correct: ``(C, R)`` samples with the right recognised fault set.
        sq_err: ``(C, R, n)`` summed squared state errors.
        health: ``(C, R)`` OR of the health flags.
        fdi_faulty: ``(C, R)`` the run's :class:`~uimm_jax.engine.metrics.FDICounts`,
            one array per count (``fdi_flagged_faulty``, ``fdi_flagged_free``,
            ``fdi_true_prob`` likewise).
        nis: ``(C, R)`` summed NIS per channel of the leading model (``RunMetrics.nis``).
        unexplained: ``(C, R)`` first step of the run's first unexplained spell (-1: none;
            ``RunMetrics.spells``).
        nis_channels: ``(C, R, m)`` summed per-output NIS of the leading model
            (``RunMetrics.nis_channels``).
        est_retract_step: ``(C, R, F)`` the size-estimating method's retraction steps
            (-1); ``est_declarations`` ``(C, R, F)``, ``est_false_count`` ``(C, R)``,
            ``est_magnitude`` and ``est_magnitude_sd`` ``(C, R, F)`` (NaN) likewise
            (:class:`~uimm_jax.engine.metrics.EstMetrics`; their "none" values for the
            other methods' runs).
    """

    done: np.ndarray
    decl_step: np.ndarray
    correct: np.ndarray
    sq_err: np.ndarray
    health: np.ndarray
    fdi_faulty: np.ndarray
    fdi_flagged_faulty: np.ndarray
    fdi_flagged_free: np.ndarray
    fdi_true_prob: np.ndarray
    nis: np.ndarray
    unexplained: np.ndarray
    nis_channels: np.ndarray
    est_retract_step: np.ndarray
    est_declarations: np.ndarray
    est_false_count: np.ndarray
    est_magnitude: np.ndarray
    est_magnitude_sd: np.ndarray

    @classmethod
    def empty(cls, C: int, R: int, F: int, n: int, m: int = 1) -> Finished:
        """No run finished (``C`` cells, ``R`` runs, ``F`` faults, ``n`` states, ``m`` outputs)."""
        return cls(
            done=np.zeros((C, R), np.uint8),
            decl_step=np.full((C, R, F), -1, np.int32),
            correct=np.zeros((C, R), np.int64),
            sq_err=np.zeros((C, R, n)),
            health=np.zeros((C, R), np.int32),
            fdi_faulty=np.zeros((C, R), np.int64),
            fdi_flagged_faulty=np.zeros((C, R), np.int64),
            fdi_flagged_free=np.zeros((C, R), np.int64),
            fdi_true_prob=np.zeros((C, R)),
            nis=np.zeros((C, R)),
            unexplained=np.full((C, R), -1, np.int32),
            nis_channels=np.zeros((C, R, m)),
            est_retract_step=np.full((C, R, F), -1, np.int32),
            est_declarations=np.zeros((C, R, F), np.int32),
            est_false_count=np.zeros((C, R), np.int32),
            est_magnitude=np.full((C, R, F), np.nan),
            est_magnitude_sd=np.full((C, R, F), np.nan),
        )


def manifest_for(scenario, spec, dtype, batch: int, devices: int) -> dict:
    """The record of what a sweep computes (JSON values only).

    Args:
        scenario: the scenario.
        spec: the :class:`~uimm_jax.scenario.sweep.SweepSpec`.
        dtype: the float dtype.
        batch: runs per batch actually used (all devices).
        devices: the number of devices the runs are sharded over.
    """
    sc = scenario_to_dict(scenario)
    sc.pop("sweep", None)  # its fields are in the settings
    settings = dict(spec_settings(spec), dtype=np.dtype(dtype).name)
    layout = {"batch": int(batch), "devices": int(devices)}
    doc = {"format": FORMAT, "scenario": sc, "settings": settings, "layout": layout}
    return json.loads(json.dumps(doc))


def _differences(old: Any, new: Any, path: str) -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for key in list(old) + [k for k in new if k not in old]:
            out += _differences(old.get(key), new.get(key), f"{path}.{key}")
        return out
    if old == new:
        return []
    return [f"{path} ({_short(old)} then, {_short(new)} now)"]


def _short(value: Any) -> str:
    text = "absent" if value is None else json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _atomic_write(path: Path, write: Callable) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        write(fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    try:  # make the rename itself durable
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory descriptors
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class SweepStore:
    """A checkpoint folder (see the module doc); only process 0 holds one.

    Attributes:
        folder: the folder.
        manifest: the record of the sweep (:func:`manifest_for` plus progress fields).
    """

    def __init__(self, folder: Path, manifest: dict):
        self.folder = folder
        self.manifest = manifest

    def batches(self) -> list[Path]:
        """The batch files, in the order they were written."""
        return sorted(self.folder.glob("batch-*.npz"))

    def write_manifest(self, **fields) -> None:
        """Write the manifest (atomically), updated with ``fields``."""
        self.manifest.update(fields)
        text = (json.dumps(self.manifest, indent=1) + "\n").encode()
        _atomic_write(self.folder / MANIFEST, lambda fh: fh.write(text))

    def save_batch(self, cells: np.ndarray, runs: np.ndarray, **arrays: np.ndarray) -> Path:
        """Write one finished batch: its runs' indices and per-run arrays.

        Args:
            cells: ``(B,)`` cell index of each run of the batch (no padding).
            runs: ``(B,)`` run index of each.
            **arrays: their ``decl_step (B, F)``, ``correct (B,)``, ``sq_err (B, n)``,
                ``health (B,)``, FDI counts (``fdi_*``, ``(B,)``) and the size-estimating
                method's ``est_*`` arrays (:class:`Finished`).
        """
        if sorted(arrays) != sorted(_FIELDS + _EST_FIELDS):
            raise ValueError(
                f"save_batch: expected the arrays {_FIELDS + _EST_FIELDS}, got {sorted(arrays)}"
            )
        path = self.folder / f"batch-{len(self.batches()):05d}.npz"
        _atomic_write(path, lambda fh: np.savez(fh, cell=cells, run=runs, **arrays))
        return path

    def load(self, shape: tuple[int, ...]) -> Finished:
        """The finished runs of every batch file, as ``(C, R, ...)`` arrays.

        A batch file written before the size arrays were stored (no ``est_*``) is read
        when the sweep has no size-estimating method (its runs keep the "none" values),
        and refused otherwise.

        Args:
            shape: ``(C, R, F, n[, m])``: cells, runs, faults, states and outputs.
        """
        fin = Finished.empty(*shape)
        sizes = UIMMEstDiagnoser.method in (self.manifest.get("settings") or {}).get("methods", ())
        for path in self.batches():
            try:
                with np.load(path) as z:
                    c, r = z["cell"], z["run"]
                    names = _FIELDS + (_EST_FIELDS if sizes or "est_magnitude" in z else ())
                    for name in names:
                        getattr(fin, name)[c, r] = z[name]
                    fin.done[c, r] = 1
            except (OSError, KeyError, ValueError, IndexError) as err:
                raise ValueError(
                    f"--resume: {path} is not a batch of this sweep ({err}); delete it to "
                    "recompute its runs"
                ) from None
        return fin


def _open(folder: Path, manifest: dict, resume: bool, shape) -> tuple[SweepStore, Finished]:
    """Process 0's part of :func:`open_store`."""
    folder.mkdir(parents=True, exist_ok=True)
    for tmp in folder.glob(".*.tmp"):
        tmp.unlink()
    path = folder / MANIFEST
    old = None
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise ValueError(
                f"{path}: unreadable ({err}); delete {folder} to start afresh"
            ) from None
    store = SweepStore(folder, dict(manifest))
    if resume:
        if old is None:
            raise ValueError(
                f"--resume: {folder} holds no sweep to resume (no {MANIFEST}); run without "
                "--resume to start one"
            )
        diffs = _differences({k: old.get(k) for k in manifest}, manifest, "")
        if diffs:
            hint = ""
            if any(d.startswith(".layout") for d in diffs):
                lay = old.get("layout") or {}
                hint = (
                    f" (the batch layout: give --batch {lay.get('batch')} and run on "
                    f"{lay.get('devices')} device(s) in all; it decides the last bits of the "
                    "state errors)"
                )
            raise ValueError(
                f"--resume: the sweep in {folder} was run with another scenario or other "
                "settings: "
                + "; ".join(d.lstrip(".") for d in diffs[:8])
                + ("; ..." if len(diffs) > 8 else "")
                + ". Resume with the same scenario and settings"
                + hint
                + ", or write to another --out"
            )
        finished = store.load(shape)
    else:
        if old is not None and not old.get("complete", False):
            done = int(store.load(shape).done.sum()) if old.get("format") == FORMAT else 0
            raise ValueError(
                f"--out: {folder} holds an unfinished sweep ({done} runs finished); "
                f"continue it with --resume, or delete {folder}, or choose another --out"
            )
        for stale in store.batches():
            stale.unlink()
        finished = Finished.empty(*shape)
    store.write_manifest(complete=False, runs_total=int(shape[0] * shape[1]))
    return store, finished


def open_store(
    folder, manifest: dict, *, resume: bool, shape: tuple[int, ...]
) -> tuple[SweepStore | None, Finished]:
    """Open a checkpoint folder for a sweep (on every process of a multi-process sweep).

    Args:
        folder: the checkpoint folder (created).
        manifest: :func:`manifest_for` of the sweep.
        resume: continue the sweep recorded there (else start afresh, refusing a folder
            that holds an unfinished sweep).
        shape: ``(C, R, F, n[, m])``: cells, runs, faults, states and measured outputs
            (``m`` 1 when left out).

    Returns:
        ``(store, finished)``: the store on process 0 (``None`` on the others) and the
        runs already finished (none unless resuming), on every process.

    Raises:
        ValueError: the refusals of the module doc, with the reason (on process 0; the
            other processes raise a shorter error pointing to process 0's).
    """
    store, error = None, None
    finished = Finished.empty(*shape)
    if is_main():
        try:
            store, finished = _open(Path(folder), manifest, resume, shape)
        except (OSError, ValueError) as err:
            error = err
    failed, finished = share((np.array(error is not None, np.uint8), finished))
    if error is not None:
        raise error if isinstance(error, ValueError) else ValueError(f"{folder}: {error}")
    if failed:
        raise ValueError(f"{folder}: process 0 refused the checkpoint (its error says why)")
    return store, Finished(*finished)
