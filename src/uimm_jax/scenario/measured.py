"""Measured data: read a user's measurements (CSV, ``.npy`` or ``.npz``) for a scenario.

The diagnoser of a scenario (:func:`uimm_jax.studies.run.setup_scenario`) runs over measured
data exactly as over simulated data.  The file layout is documented in
``docs/measurements.md``; in short:

* **CSV** (``.csv``): a header row naming the columns, then one row per sample.  One
  column per measured output, named as the plant's ``output_names`` (for the hydraulic
  actuator ``x_p, v_p, p_h``), in any order; an optional ``t`` column (s); optional input
  columns named as the plant's ``input_names`` (``i_v``) -- all of them or none.  Lines
  starting with ``#`` are comments.  An empty cell or ``nan`` is a *missing* measurement.
* **``.npy``**: one ``(N, m)`` array of measurements, columns in ``output_names`` order.
* **``.npz``**: arrays ``y`` ``(N, m)`` and optionally ``u`` ``(N, p)`` and ``t`` ``(N,)``.

Sample ``k`` (0-based) is the measurement at ``t_k = (k + 1) dt`` (the runner's time
convention: the state after the ``k``-th transition, driven by the input ``u_k = u(k dt)``),
so a ``t`` column must read ``dt, 2 dt, 3 dt, ...``; without inputs in the file the
scenario's input signal is used.  A missing measurement (NaN) is not used by the filter
(the models predict only on that channel; when every channel of a sample is missing the
mode probabilities follow the Markov prediction).  Infinite values are refused, as are
missing inputs or times.

:func:`load_measurements` returns a :class:`MeasuredData`, which
:func:`uimm_jax.studies.run.run_scenario` accepts as ``measurements=`` (the CLI's
``uimm-jax run SCENARIO --measurements FILE``).  :func:`degrade_measurements` makes the
dropouts and outliers of the robustness study (``docs/robustness.md``).
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import io
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from uimm_jax.errors import UIMMWarning

__all__ = [
    "MeasuredData",
    "MeasurementError",
    "TIME_TOLERANCE",
    "degrade_measurements",
    "load_measurements",
    "measured_data",
]

#: A ``t`` column may deviate from ``(k + 1) dt`` by this fraction of ``dt``.
TIME_TOLERANCE = 0.01

_MISSING_WORDS = ("", "nan", "-nan", "+nan")


class MeasurementError(ValueError):
    """An invalid measurement file or array.

    The message reads ``"<source>: <where>: <problem and fix>"``.

    Args:
        detail: what is wrong and what is expected instead.
        source: the file name (or ``"<array>"``).
        where: the column, line or array concerned (or ``None``).
    """

    def __init__(self, detail: str, *, source: str, where: str | None = None):
        self.detail = detail
        self.source = source
        self.where = where
        # An array passed as ``measurements=`` has that name as its source: say it once.
        shown = where if where and where != source else None
        super().__init__(f"{source}: " + (f"{shown}: " if shown else "") + detail)


@dataclasses.dataclass(frozen=True, eq=False)
class MeasuredData:
    """Measurements (and optionally inputs and times) for one scenario run.

    ``np.asarray(data)`` gives ``y``, so a :class:`MeasuredData` can be used wherever an
    ``(N, m)`` measurement array is expected.

    Attributes:
        y: ``(N, m)`` float64 measurements in ``plant.output_names`` order; NaN = missing.
        u: ``(N, p)`` float64 inputs in ``plant.input_names`` order, or ``None`` (then the
            scenario's input signal is used).
        t: ``(N,)`` sample times from the file, or ``None``.
        source: where the data came from (file name or ``"<array>"``).
    """

    y: np.ndarray
    u: np.ndarray | None = None
    t: np.ndarray | None = None
    source: str = "<array>"

    def __array__(self, dtype=None, copy=None):
        """The measurements ``y`` as an array."""
        return self.y if dtype is None else self.y.astype(dtype)

    @property
    def num_steps(self) -> int:
        """Number of samples ``N``."""
        return int(self.y.shape[0])

    @property
    def missing_fraction(self) -> float:
        """Fraction of missing (NaN) entries of ``y``."""
        return float(np.mean(np.isnan(self.y))) if self.y.size else 0.0


# --------------------------------------------------------------------------------------
# Validation shared by every format
# --------------------------------------------------------------------------------------


def _plant_of(scenario):
    plant = getattr(scenario, "plant", None)
    if plant is None or not hasattr(plant, "output_names"):
        raise TypeError(
            "scenario: expected a uimm_jax.Scenario (load it with "
            f"uimm_jax.load_scenario), got {type(scenario).__name__}"
        )
    return plant


def _numeric(a: Any, source: str, where: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.dtype == object or arr.dtype.kind not in "biuf":
        kind = "complex" if arr.dtype.kind == "c" else str(arr.dtype)
        raise MeasurementError(
            f"expected an array of real numbers, got dtype {kind}", source=source, where=where
        )
    return arr.astype(np.float64)


def measured_data(scenario, y, u=None, t=None, *, source: str = "<array>") -> MeasuredData:
    """Validate arrays against a scenario and pack them into a :class:`MeasuredData`.

    Args:
        scenario: the :class:`~uimm_jax.scenario.spec.Scenario` (its plant gives ``m``, ``p``
            and its ``dt`` the time grid).
        y: ``(N, m)`` measurements (``(N,)`` when ``m = 1``); NaN = missing, inf refused.
        u: optional ``(N, p)`` inputs (``(N,)`` when ``p = 1``), all finite.
        t: optional ``(N,)`` sample times; must be ``(k + 1) dt`` within
            :data:`TIME_TOLERANCE` of ``dt``.
        source: name used in error messages.

    Returns:
        The validated :class:`MeasuredData` (float64 copies).

    Raises:
        MeasurementError: wrong shape, non-numeric, infinite or badly timed data.
    """
    plant = _plant_of(scenario)
    m, p = plant.output_dim, plant.input_dim
    names = ", ".join(plant.output_names)
    ya = _numeric(y, source, "measurements")
    if ya.ndim == 1 and m == 1:
        ya = ya[:, None]
    if ya.ndim != 2 or ya.shape[1] != m:
        raise MeasurementError(
            f"expected shape (N, {m}) -- one column per output ({names}) -- got {ya.shape}",
            source=source,
            where="measurements",
        )
    if ya.shape[0] == 0:
        raise MeasurementError("no samples (N = 0)", source=source, where="measurements")
    bad = np.isinf(ya)
    if np.any(bad):
        k, c = (int(v) for v in np.argwhere(bad)[0])
        raise MeasurementError(
            f"sample {k}, output {plant.output_names[c]!r} is {ya[k, c]}; infinite values "
            "are not measurements -- write NaN (or an empty CSV cell) for a missing one",
            source=source,
            where="measurements",
        )
    N = ya.shape[0]
    ua = None
    if u is not None:
        ua = _numeric(u, source, "inputs")
        if ua.ndim == 1 and p == 1:
            ua = ua[:, None]
        if ua.shape != (N, p):
            raise MeasurementError(
                f"expected shape ({N}, {p}) -- one row per sample, one column per input "
                f"({', '.join(plant.input_names)}) -- got {ua.shape}",
                source=source,
                where="inputs",
            )
        if not np.all(np.isfinite(ua)):
            k, c = (int(v) for v in np.argwhere(~np.isfinite(ua))[0])
            raise MeasurementError(
                f"sample {k}, input {plant.input_names[c]!r} is {ua[k, c]}; inputs may not be "
                "missing or infinite (the filter needs every input to predict)",
                source=source,
                where="inputs",
            )
    ta = None
    if t is not None:
        ta = _numeric(t, source, "t").reshape(-1)
        if ta.shape != (N,):
            raise MeasurementError(
                f"expected {N} sample times, got {ta.size}", source=source, where="t"
            )
        _check_times(ta, float(scenario.dt), source)
    return MeasuredData(ya.copy(), None if ua is None else ua.copy(), ta, source)


def _check_times(t: np.ndarray, dt: float, source: str, lines: list[int] | None = None) -> None:
    if not np.all(np.isfinite(t)):
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        where = f"line {lines[k]}" if lines else f"t[{k}]"
        raise MeasurementError(
            f"time {t[k]} is not a finite number; every sample needs its time",
            source=source,
            where=where,
        )
    expected = (np.arange(t.size) + 1.0) * dt
    off = np.abs(t - expected) > TIME_TOLERANCE * dt
    if np.any(off):
        k = int(np.flatnonzero(off)[0])
        where = f"line {lines[k]}, column 't'" if lines else f"t[{k}]"
        hint = ""
        if k == 0 and abs(t[0]) <= TIME_TOLERANCE * dt:
            hint = (
                " (your times start at 0: sample k is the measurement after the k-th step, "
                "at (k + 1) dt -- add dt to the column, or drop it)"
            )
        raise MeasurementError(
            f"t = {float(t[k])!r} but sample {k} must be at (k + 1) dt = {float(expected[k])!r} s "
            f"(dt = {dt!r} s from the scenario, tolerance {TIME_TOLERANCE:g} dt){hint}; "
            "the samples must be uniformly spaced by the scenario's dt",
            source=source,
            where=where,
        )


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------


def load_measurements(path, scenario) -> MeasuredData:
    """Read measured data for ``scenario`` from a CSV, ``.npy`` or ``.npz`` file.

    The layout is documented in ``docs/measurements.md`` and in this module's docstring.
    A file whose number of samples differs from ``scenario.num_steps`` is accepted with a
    :class:`~uimm_jax.errors.UIMMWarning` (the run then covers the file's samples).

    Args:
        path: the file (``.csv``, ``.npy`` or ``.npz``).
        scenario: the :class:`~uimm_jax.scenario.spec.Scenario` the data belongs to.

    Returns:
        A :class:`MeasuredData`.

    Raises:
        MeasurementError: a missing, unreadable or malformed file; the message names the
            line or column and says what is expected.
    """
    plant = _plant_of(scenario)
    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise MeasurementError(
            "file not found" + (" (it is a directory)" if path.is_dir() else ""),
            source=source,
        )
    suffix = path.suffix.lower()
    if suffix == ".csv":
        data = _load_csv(path, scenario, plant)
    elif suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as err:  # noqa: BLE001 - any read failure becomes a clear message
            raise MeasurementError(f"not a readable .npy array ({err})", source=source) from None
        if not isinstance(arr, np.ndarray) or arr.dtype.names is not None:
            raise MeasurementError(
                "expected a plain (N, m) numeric array (not a structured array)", source=source
            )
        data = measured_data(scenario, arr, source=source)
    elif suffix == ".npz":
        data = _load_npz(path, scenario, source)
    else:
        raise MeasurementError(
            f"unknown file type {path.suffix!r}; expected .csv, .npy or .npz "
            "(see docs/measurements.md)",
            source=source,
        )
    if data.num_steps != scenario.num_steps:
        warnings.warn(
            f"{source}: {data.num_steps} samples, the scenario has {scenario.num_steps}; "
            f"the run covers the file's {data.num_steps} samples "
            f"({data.num_steps * float(scenario.dt):g} s)",
            UIMMWarning,
            stacklevel=2,
        )
    return data


def _load_npz(path: Path, scenario, source: str) -> MeasuredData:
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as err:  # noqa: BLE001
        raise MeasurementError(f"not a readable .npz archive ({err})", source=source) from None
    unknown = sorted(set(arrays) - {"y", "u", "t"})
    if unknown:
        raise MeasurementError(
            f"unknown array(s) {unknown}; an .npz holds 'y' (required), 'u' and 't'",
            source=source,
        )
    if "y" not in arrays:
        raise MeasurementError(
            "missing array 'y' (the (N, m) measurements)", source=source, where="y"
        )
    return measured_data(scenario, arrays["y"], arrays.get("u"), arrays.get("t"), source=source)


def _suggest(name: str, choices) -> str:
    close = difflib.get_close_matches(name, list(choices), n=1, cutoff=0.6)
    return f" Did you mean {close[0]!r}?" if close else ""


def _load_csv(path: Path, scenario, plant) -> MeasuredData:
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as err:
        raise MeasurementError(
            f"not UTF-8 text ({err.reason} at byte {err.start}); save the CSV as UTF-8",
            source=source,
        ) from None
    rows: list[tuple[int, list[str]]] = []
    for lineno, line in enumerate(io.StringIO(text), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        cells = next(csv.reader([line]))
        rows.append((lineno, [c.strip() for c in cells]))
    outputs, inputs = plant.output_names, plant.input_names
    allowed = ("t", *outputs, *inputs)
    if not rows:
        raise MeasurementError(
            f"empty file; expected a header row ({', '.join(allowed)}) and one row per sample",
            source=source,
        )
    header_line, header = rows[0]
    where = f"line {header_line} (header)"
    if all(_is_number(c) for c in header):
        raise MeasurementError(
            "the first row must be a header naming the columns, e.g. "
            f"'{','.join(('t', *outputs, *inputs))}'",
            source=source,
            where=where,
        )
    if len(header) == 1 and any(sep in header[0] for sep in ";\t"):
        raise MeasurementError(
            f"found one column {header[0]!r}; columns must be separated by commas",
            source=source,
            where=where,
        )
    seen: dict[str, int] = {}
    for i, name in enumerate(header):
        if name == "":
            raise MeasurementError(
                f"column {i + 1} has no name; name every column", source=source, where=where
            )
        if name in seen:
            raise MeasurementError(
                f"column {name!r} appears twice (columns {seen[name] + 1} and {i + 1})",
                source=source,
                where=where,
            )
        if name not in allowed:
            raise MeasurementError(
                f"unknown column {name!r}.{_suggest(name, allowed)} Allowed columns: "
                f"t (optional), the outputs {', '.join(outputs)} (required) and the "
                f"inputs {', '.join(inputs) or '(none)'} (optional, all or none)",
                source=source,
                where=where,
            )
        seen[name] = i
    missing = [o for o in outputs if o not in seen]
    if missing:
        raise MeasurementError(
            f"missing output column(s) {', '.join(missing)}; the file needs one column per "
            f"measured output ({', '.join(outputs)}); an output never measured is a column "
            "of empty cells",
            source=source,
            where=where,
        )
    given_inputs = [i for i in inputs if i in seen]
    if given_inputs and len(given_inputs) != len(inputs):
        absent = [i for i in inputs if i not in seen]
        raise MeasurementError(
            f"input column(s) {', '.join(absent)} missing; give all inputs "
            f"({', '.join(inputs)}) or none (then the scenario's input signal is used)",
            source=source,
            where=where,
        )
    body = rows[1:]
    if not body:
        raise MeasurementError(
            "no data rows after the header", source=source, where=f"line {header_line}"
        )
    N = len(body)
    table = np.empty((N, len(header)))
    for r, (lineno, cells) in enumerate(body):
        if len(cells) != len(header):
            raise MeasurementError(
                f"{len(cells)} cells, the header has {len(header)}; every row needs one cell "
                "per column (leave a cell empty for a missing measurement)",
                source=source,
                where=f"line {lineno}",
            )
        for c, cell in enumerate(cells):
            table[r, c] = _parse_cell(cell, header[c], outputs, source, lineno)
    lines = [ln for ln, _ in body]
    y = table[:, [seen[o] for o in outputs]]
    u = table[:, [seen[i] for i in inputs]] if given_inputs else None
    t = table[:, seen["t"]] if "t" in seen else None
    if u is not None and not np.all(np.isfinite(u)):
        r, c = (int(v) for v in np.argwhere(~np.isfinite(u))[0])
        raise MeasurementError(
            f"input {inputs[c]!r} is missing; inputs may not be missing (the filter needs "
            "every input to predict) -- fill the cell or drop the input columns",
            source=source,
            where=f"line {lines[r]}, column {inputs[c]!r}",
        )
    if t is not None:
        _check_times(t, float(scenario.dt), source, lines)
    return measured_data(scenario, y, u, t, source=source)


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _parse_cell(cell: str, column: str, outputs, source: str, lineno: int) -> float:
    if cell.lower() in _MISSING_WORDS:
        return math.nan
    try:
        v = float(cell)
    except ValueError:
        raise MeasurementError(
            f"{cell!r} is not a number; write a number"
            + (
                ", or leave the cell empty (or NaN) for a missing measurement"
                if column in outputs
                else ""
            ),
            source=source,
            where=f"line {lineno}, column {column!r}",
        ) from None
    if math.isinf(v):
        raise MeasurementError(
            f"{cell!r} is infinite; "
            + (
                "a missing measurement is an empty cell or NaN"
                if column in outputs
                else "write a finite number"
            ),
            source=source,
            where=f"line {lineno}, column {column!r}",
        )
    return v


# --------------------------------------------------------------------------------------
# Robustness helper
# --------------------------------------------------------------------------------------


def degrade_measurements(
    y,
    R,
    *,
    drop_fraction: float = 0.1,
    num_outliers: int = 100,
    outlier_sigma: float = 1e6,
    seed: int = 0,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Drop measurements and add gross outliers (the robustness study's corruption).

    Each entry of ``y`` is dropped (set to NaN) independently with probability
    ``drop_fraction``; then ``num_outliers`` distinct remaining entries get
    ``+- outlier_sigma * sqrt(R[c, c])`` added (random sign).

    Args:
        y: ``(N, m)`` measurements.
        R: ``(m, m)`` measurement noise covariance (gives each channel's sigma).
        drop_fraction: probability that an entry is missing.
        num_outliers: number of outlier entries.
        outlier_sigma: outlier size in standard deviations of the channel's noise.
        seed: NumPy seed.

    Returns:
        ``(y_degraded, info)`` with ``info["dropped"]`` ``(N, m)`` bool and
        ``info["outliers"]`` ``(num_outliers, 2)`` ``(step, channel)`` indices.
    """
    rng = np.random.default_rng(seed)
    y2 = np.array(y, dtype=np.float64, copy=True)
    dropped = rng.random(y2.shape) < drop_fraction
    y2[dropped] = np.nan
    candidates = np.flatnonzero(~dropped.ravel())
    if num_outliers > candidates.size:
        raise ValueError(
            f"num_outliers: {num_outliers} outliers requested but only {candidates.size} "
            "entries are not dropped"
        )
    pick = rng.choice(candidates, size=num_outliers, replace=False)
    k, c = np.unravel_index(np.sort(pick), y2.shape)
    sigma = np.sqrt(np.diag(np.asarray(R, np.float64)))
    signs = rng.choice([-1.0, 1.0], size=num_outliers)
    y2[k, c] += signs * outlier_sigma * sigma[c]
    return y2, {"dropped": dropped, "outliers": np.stack([k, c], axis=1)}
