"""Field checks of scenario input, shared by the TOML parser and the ``[sweep]`` table.

:class:`FieldChecker` raises :class:`~uimm_jax.errors.ScenarioError` naming the source and
the field (``[filter].stay``, ``[sweep].runs``) and collects the warnings of values that
were accepted but changed.  The integer and positive-number rules are those of
:mod:`uimm_jax._checks`, worded for a file (``must be ...``).
"""

from __future__ import annotations

import datetime
import difflib
import math
import numbers
import re
from collections.abc import Iterable, Mapping
from typing import Any, NoReturn

import numpy as np

from uimm_jax._checks import integer_problem, is_number, positive_problem, type_name
from uimm_jax.engine.truth import GROWTH_KINDS
from uimm_jax.errors import ScenarioError
from uimm_jax.plants.base import Plant
from uimm_jax.scenario.spec import PSD_RTOL, SYMMETRY_RTOL

__all__ = ["FieldChecker", "frozen", "plain", "suggest", "toml_key", "toml_string"]


def suggest(word: str, choices: Iterable[str]) -> str:
    """`` Did you mean ...?`` for the choice closest to ``word``, or ``""``."""
    choices = list(choices)
    lowered = {c.lower(): c for c in choices}
    close = difflib.get_close_matches(word.lower(), list(lowered), n=1, cutoff=0.6)
    return f" Did you mean {lowered[close[0]]!r}?" if close else ""


def frozen(array: np.ndarray) -> np.ndarray:
    """A read-only float64 copy: scenarios are immutable."""
    out = np.array(array, dtype=np.float64)
    out.setflags(write=False)
    return out


def plain(value: Any, where: str, source: str) -> Any:
    """Turn NumPy arrays/scalars and tuples into the plain types ``tomllib`` produces."""
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ScenarioError(
                    f"keys must be strings, got {k!r} ({type(k).__name__})",
                    source=source,
                    field=where or "top level",
                )
            out[k] = plain(v, f"{where}.{k}" if where else k, source)
        return out
    if isinstance(value, np.ndarray):
        return plain(value.tolist(), where, source)
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, list | tuple):
        return [plain(v, where, source) for v in value]
    return value


_ESCAPES = {
    '"': '\\"',
    "\\": "\\\\",
    "\b": "\\b",
    "\t": "\\t",
    "\n": "\\n",
    "\f": "\\f",
    "\r": "\\r",
}


def toml_string(text: str) -> str:
    """A TOML basic string (quoted, escaped)."""
    out = []
    for ch in text:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def toml_key(name: str) -> str:
    """A TOML key: bare if possible, else a quoted basic string."""
    return name if re.fullmatch(r"[A-Za-z0-9_-]+", name) else toml_string(name)


class FieldChecker:
    """Checks of one scenario's fields; collects warnings to be emitted by the caller.

    Args:
        source: where the scenario came from (a file name or ``"<dict>"``), or ``None``.

    Attributes:
        notes: the warnings collected (``"<source>: <field>: <detail>"``).
    """

    HINTS: Mapping[str, str] = {}
    """What to write for a missing required key, by key."""

    def __init__(self, source: str | None):
        self.source = source
        self.notes: list[str] = []

    # -- error helpers ------------------------------------------------------------------

    def fail(self, field: str | None, detail: str) -> NoReturn:
        raise ScenarioError(detail, source=self.source, field=field)

    def warn(self, field: str, detail: str) -> None:
        self.notes.append(f"{self.source}: {field}: {detail}")

    @staticmethod
    def path(header: str, key: str) -> str:
        return f"{header}.{toml_key(key)}" if header else toml_key(key)

    def keys(
        self,
        table: Mapping[str, Any],
        header: str,
        allowed: tuple[str, ...],
        required: tuple[str, ...] = (),
    ) -> None:
        where = header or "the top level"
        for key in table:
            if key not in allowed:
                self.fail(
                    self.path(header, key),
                    f"unknown key {key!r} in {where}.{suggest(key, allowed)} "
                    f"Allowed keys: {', '.join(allowed)}.",
                )
        for key in required:
            if key not in table:
                hint = self.HINTS.get(key, "")
                self.fail(
                    self.path(header, key),
                    f"required key is missing from {where}" + (f"; give {hint}." if hint else "."),
                )

    def table(self, value: Any, field: str, what: str = "") -> Mapping[str, Any]:
        if not isinstance(value, Mapping):
            hint = ""
            if field.startswith("[") and not field.startswith("[["):
                hint = f" Write it as a {field} section (or an inline table {{...}})."
            self.fail(field, f"must be a table{what}, got {type_name(value)}.{hint}")
        return value

    def number(
        self,
        value: Any,
        field: str,
        *,
        low: float | None = None,
        high: float | None = None,
        low_open: bool = False,
        high_open: bool = False,
        unit: str = "",
    ) -> float:
        unit_txt = f" {unit}" if unit else ""
        if not is_number(value):
            self.fail(field, f"must be a number{unit_txt}, got {type_name(value)}.")
        x = float(value)
        if not math.isfinite(x):
            self.fail(field, f"must be a finite number{unit_txt}, got {x!r}.")
        too_low = low is not None and (x <= low if low_open else x < low)
        too_high = high is not None and (x >= high if high_open else x > high)
        if too_low or too_high:
            lo = "-inf" if low is None else repr(low)
            hi = "inf" if high is None else repr(high)
            interval = ("(" if low_open or low is None else "[") + f"{lo}, {hi}"
            interval += ")" if high_open or high is None else "]"
            self.fail(field, f"must be in {interval}{unit_txt}, got {x!r}.")
        return x

    def integer(self, value: Any, field: str, *, low: int, high: int | None = None) -> int:
        problem = integer_problem(value, low, high)
        if problem:
            self.fail(field, f"must be {problem}.")
        return int(value)

    def positive(self, value: Any, field: str) -> float:
        """A finite number > 0."""
        problem = positive_problem(value)
        if problem:
            self.fail(field, f"must be {problem}.")
        return float(value)

    def boolean(self, value: Any, field: str) -> bool:
        if not isinstance(value, bool):
            self.fail(field, f"must be true or false, got {type_name(value)}.")
        return value

    def growth(
        self, entry: Mapping[str, Any], field: str, ramp: float, ramp_axis: bool = False
    ) -> str:
        """An event's ``growth`` (``field``: the event's header), one of ``GROWTH_KINDS``.

        ``"exponential"`` needs a ``ramp`` > 0 (its time constant), unless a sweep's
        ``ramps`` axis gives it (``ramp_axis``; a cell of 0 is then abrupt).
        """
        value = entry.get("growth", GROWTH_KINDS[0])
        where = f"{field}.growth"
        kinds = ", ".join(GROWTH_KINDS)
        if not isinstance(value, str):
            self.fail(where, f"must be a string, one of {kinds}; got {type_name(value)}.")
        if value not in GROWTH_KINDS:
            self.fail(
                where,
                f"unknown growth {value!r}.{suggest(value, GROWTH_KINDS)} Expected one of: "
                f"{kinds}.",
            )
        if value != GROWTH_KINDS[0] and ramp <= 0 and not ramp_axis:
            self.fail(
                where,
                f"{value!r} needs {field}.ramp > 0 (or a [sweep] ramps axis): for this growth "
                "the ramp is the time constant tau (s) of magnitude * (1 - exp(-(t - time) / "
                "tau)).",
            )
        return str(value)

    def string(self, value: Any, field: str) -> str:
        if not isinstance(value, str):
            self.fail(field, f"must be a string, got {type_name(value)}.")
        if not value.strip():
            self.fail(field, "must be a non-empty string.")
        return value

    def vector(self, value: Any, field: str, length: int, what: str) -> np.ndarray:
        if not isinstance(value, list):
            self.fail(
                field, f"must be an array of {length} numbers ({what}), got {type_name(value)}."
            )
        if len(value) != length:
            self.fail(field, f"expected {length} entries ({what}), got {len(value)}.")
        return np.array(
            [self.number(v, f"{field}[{i}]") for i, v in enumerate(value)], dtype=np.float64
        )

    def matrix(self, value: Any, field: str, size: int, what: str) -> np.ndarray:
        if not isinstance(value, list) or not all(isinstance(r, list) for r in value):
            self.fail(
                field, f"must be a {size} x {size} matrix (an array of {size} arrays; {what})."
            )
        if len(value) != size:
            self.fail(field, f"expected a {size} x {size} matrix ({what}), got {len(value)} rows.")
        for i, row in enumerate(value):
            if len(row) != size:
                self.fail(
                    field,
                    f"row {i} has {len(row)} entries; expected a {size} x {size} matrix ({what}).",
                )
        return np.array(
            [
                [self.number(v, f"{field}[{i}][{j}]") for j, v in enumerate(row)]
                for i, row in enumerate(value)
            ],
            dtype=np.float64,
        )

    def covariance(
        self,
        value: Any,
        field: str,
        names: tuple[str, ...],
        *,
        definite: bool,
        symbol: str,
    ) -> np.ndarray:
        """Scalar (times I), diagonal (list of n) or full n x n symmetric PSD/PD matrix."""
        size = len(names)
        what = f"{symbol}, one per {', '.join(names)}"
        need = "positive definite" if definite else "positive semi-definite"
        sign = "> 0" if definite else ">= 0"
        if is_number(value):
            c = self.number(value, field, low=0.0, low_open=definite)
            return c * np.eye(size)
        if isinstance(value, list) and value and all(isinstance(r, list) for r in value):
            mat = self.matrix(value, field, size, what)
        elif isinstance(value, list) and all(not isinstance(r, list) for r in value):
            if len(value) != size:
                self.fail(
                    field,
                    f"expected {size} entries (the diagonal of {what}) or a {size} x {size} "
                    f"matrix, got {len(value)} entries.",
                )
            diag = self.vector(value, field, size, f"the diagonal of {what}")
            for i, d in enumerate(diag):
                if not (d > 0 if definite else d >= 0):
                    self.fail(
                        f"{field}[{i}]",
                        f"diagonal entries of {symbol} must be {sign} ({symbol} must be "
                        f"{need}), got {float(d)!r} for {names[i]}.",
                    )
            return np.diag(diag)
        else:
            self.fail(
                field,
                f"must be a number (times I), an array of {size} numbers (the diagonal of "
                f"{symbol}) or a {size} x {size} matrix, got {type_name(value)}.",
            )
        scale = float(np.max(np.abs(mat))) if mat.size else 0.0
        asym = float(np.max(np.abs(mat - mat.T))) if mat.size else 0.0
        if asym > SYMMETRY_RTOL * scale:
            i, j = np.unravel_index(np.argmax(np.abs(mat - mat.T)), mat.shape)
            self.fail(
                field,
                f"{symbol} must be symmetric: entry [{i}][{j}] = {float(mat[i, j])!r} but "
                f"[{j}][{i}] = {float(mat[j, i])!r} (tolerance {SYMMETRY_RTOL} relative to "
                f"max|{symbol}|).",
            )
        if asym > 0.0:
            mat = 0.5 * (mat + mat.T)
            self.warn(
                field,
                f"{symbol} was symmetric only to {asym:.3g}; replaced by "
                f"({symbol} + {symbol}^T) / 2.",
            )
        eig = np.linalg.eigvalsh(mat)
        emax = float(np.max(np.abs(eig))) if eig.size else 0.0
        if definite:
            try:
                np.linalg.cholesky(mat)
                ok = bool(np.all(eig > 0.0))
            except np.linalg.LinAlgError:
                ok = False
        else:
            ok = bool(np.all(eig >= -PSD_RTOL * emax))
        if not ok:
            self.fail(
                field,
                f"{symbol} must be {need}; its smallest eigenvalue is {float(eig.min())!r} "
                f"(largest |eigenvalue| {emax!r}).",
            )
        return mat

    def onset_step(self, time: float, field: str, dt: float, num_steps: int) -> int:
        """The sample a fault starting at ``time`` acts from; refused past the last one."""
        step = int(round(time / dt))  # the sample the fault acts from (the truth plan)
        if step >= num_steps:
            self.fail(
                field,
                f"onset {time!r} s acts from sample round(time / dt) = {step}, but the run's "
                f"samples are 0..{num_steps - 1}: the fault would never occur. Move the "
                f"onset before {(num_steps - 0.5) * dt!r} s.",
            )
        return step

    def end_time(
        self, value: Any, field: str, time: float, step: int, dt: float, duration: float
    ) -> float:
        """The end of a fault event (s): after its onset's sample and before the run's end."""
        end = self.number(
            value,
            field,
            low=time,
            low_open=True,
            high=duration,
            high_open=True,
            unit="(s; after the event's time and before the run's end)",
        )
        if int(round(end / dt)) <= step:
            self.fail(
                field,
                f"end {end!r} s acts from sample {int(round(end / dt))}, not after the "
                f"onset's sample {step}: the fault would never be present.",
            )
        return end

    def writable(self, value: Any, field: str) -> None:
        """Check that a raw value (the ``[sweep]`` table) holds only TOML types."""
        if isinstance(value, Mapping):
            for k, v in value.items():
                self.writable(v, f"{field}.{toml_key(k)}")
        elif isinstance(value, list):
            for i, v in enumerate(value):
                self.writable(v, f"{field}[{i}]")
        elif not isinstance(value, str | numbers.Real | datetime.date | datetime.time):
            self.fail(
                field,
                f"{type_name(value)} cannot be written to TOML; use strings, numbers, "
                "booleans, dates, arrays and tables only.",
            )

    def plant_positive(self, plant: Plant, key: str, value: float, field: str) -> float:
        """Refuse a value <= 0 of a parameter the plant declares physically positive."""
        if key in plant.positive_params and not value > 0:
            self.fail(
                field,
                f"{key} must be > 0 (plant {plant.name!r} declares it physically positive: "
                f"{', '.join(plant.positive_params)}), got {value!r}.",
            )
        return value

    def param_name(self, key: str, field: str, plant: Plant) -> None:
        if key not in plant.param_names:
            self.fail(
                field,
                f"unknown parameter {key!r} of plant {plant.name!r}."
                f"{suggest(key, plant.param_names)} Known parameters: "
                f"{', '.join(plant.param_names)}.",
            )
