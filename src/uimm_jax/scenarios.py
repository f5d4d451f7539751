"""Scenario files: read, validate and write the TOML description of one experiment.

A scenario fixes everything a run needs: the plant and its parameter overrides, the input
signal, the noise covariances, the fault library (which faults the bank can diagnose),
the true fault events, and the filter settings (method, transition matrix or
self-transition probability, initial mode probabilities and state, decision rule).
The schema is documented key by key in ``docs/scenarios.md``.

Loading is strict: every problem raises :class:`~uimm_jax.errors.ScenarioError`, whose
message names the file, the field (``[filter].transition``) and what is expected.
Values that are accepted but changed (initial mode probabilities that do not sum to 1)
raise a :class:`~uimm_jax.errors.UIMMWarning` saying what was changed.

Example::

    scenario = load_scenario("scenarios/paper_sim1.toml")
    scenario.num_steps            # 1_000_000
    scenario.transition_matrix()  # (4, 4), paper eq. (37)
    dump_scenario(scenario, "copy.toml")   # load_scenario("copy.toml") gives it back

This module is pure Python/NumPy (stdlib ``tomllib``); it imports no JAX.
"""

from __future__ import annotations

import copy
import dataclasses
import datetime
import difflib
import math
import numbers
import os
import re
import tomllib
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from uimm_jax.errors import ScenarioError, UIMMWarning
from uimm_jax.models import Plant, get_plant, list_plants
from uimm_jax.validation import MAX_INT32, MAX_SEED

__all__ = [
    "DecisionSpec",
    "EventSpec",
    "FilterSpec",
    "InputSpec",
    "Scenario",
    "INPUT_KINDS",
    "METHODS",
    "dump_scenario",
    "load_scenario",
    "parse_scenario",
    "scenario_to_dict",
    "scenario_to_toml",
]

INPUT_KINDS = ("sine", "square", "step", "constant")
"""Input signal shapes understood by :class:`InputSpec`."""

METHODS = ("uimm", "imm")
"""Filter-bank methods: the updated IMM (F + 1 models) or the combinatorial IMM (2**F)."""

ROW_SUM_TOL = 1e-9
"""Rows of a transition matrix must sum to 1 within this tolerance."""

PROB_SUM_TOL = 1e-9
"""Initial mode probabilities summing to 1 within this tolerance are kept as given."""

SYMMETRY_RTOL = 1e-9
"""Covariances must satisfy ``max|P - P^T| <= SYMMETRY_RTOL * max|P|``."""

PSD_RTOL = 1e-12
"""A covariance is PSD if no eigenvalue is below ``-PSD_RTOL * max|eigenvalue|``."""

DEFAULT_INITIAL_COV = 0.1
"""Default ``initial_cov``: ``0.1 * I``, the paper's ``P0|0`` (section 4.1)."""

DEFAULT_NOMINAL_PROB = 0.9
"""Default initial probability of model 0 (no new fault); the rest share ``0.1`` equally."""


# --------------------------------------------------------------------------------------
# Data classes
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class InputSpec:
    """The input signal ``u(t)`` (for the hydraulic actuator: servo current, A).

    * ``sine``: ``offset + amplitude * sin(2 pi frequency t)``;
    * ``square``: ``offset + amplitude * sign(sin(2 pi frequency t))``, with ``+1`` where
      the sine is ``>= 0``: the first half of each period high, the second low;
    * ``step``: ``offset`` before ``step_time``, ``offset + amplitude`` from it on;
    * ``constant``: ``offset + amplitude``.

    Attributes:
        kind: one of :data:`INPUT_KINDS`.
        amplitude: amplitude in input units.
        frequency: Hz, for ``sine`` and ``square`` only.
        offset: constant added to the signal.
        step_time: s, for ``step`` only.
    """

    kind: str
    amplitude: float
    frequency: float = 1.0
    offset: float = 0.0
    step_time: float = 0.0

    def evaluate(self, t: Any, xp: Any = np) -> Any:
        """The signal at times ``t``.

        Args:
            t: times in seconds (scalar or array).
            xp: array namespace, ``numpy`` by default; ``jax.numpy`` works too.

        Returns:
            ``u(t)``, with the shape of ``t``.
        """
        t = xp.asarray(t)
        if self.kind == "sine":
            shape = xp.sin(2.0 * np.pi * self.frequency * t)
        elif self.kind == "square":
            shape = xp.where(xp.sin(2.0 * np.pi * self.frequency * t) >= 0.0, 1.0, -1.0)
        elif self.kind == "step":
            shape = xp.where(t >= self.step_time, 1.0, 0.0)
        elif self.kind == "constant":
            shape = xp.ones_like(t, dtype=float)
        else:
            raise ValueError(f"unknown input kind {self.kind!r}; expected one of {INPUT_KINDS}")
        return self.offset + self.amplitude * shape


@dataclasses.dataclass(frozen=True)
class EventSpec:
    """A true fault event: from ``time`` on, ``fault`` is present (faults are irreversible).

    Attributes:
        time: s, in ``[0, duration)``.
        fault: name of a fault of the scenario's library.
        magnitude: fraction of the nominal -> fault deviation of every parameter of the
            fault: ``value = nominal + magnitude * (fault_value - nominal)``; 1 is the
            library's fault.
    """

    time: float
    fault: str
    magnitude: float = 1.0


@dataclasses.dataclass(frozen=True)
class DecisionSpec:
    """Fault declaration rule (paper eq. 29, plus persistence).

    Attributes:
        threshold: a fault model must reach this mode probability (``mu_f`` of eq. 29),
            in ``(0, 1]``.
        hold: for this many consecutive samples (>= 1) before the fault is declared.
    """

    threshold: float = 0.9
    hold: int = 1


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class FilterSpec:
    """Filter-bank settings.

    Exactly one of ``transition`` and ``stay`` is set.  Use
    :meth:`Scenario.transition_matrix` and :meth:`Scenario.initial_mode_probs` for the
    resolved arrays.

    Attributes:
        method: ``"uimm"`` (F + 1 models) or ``"imm"`` (2**F models).
        transition: the full ``(M, M)`` Markov transition matrix as given (rows sum to 1),
            or ``None``.
        stay: self-transition probability in ``(0, 1)``, the rest spread evenly over the
            other models, or ``None``.
        initial_mode_probs: ``(M,)`` initial mode probabilities (normalised), or ``None``
            for the default (0.9 on model 0, the rest equal).
        initial_mean: ``(n,)`` initial state estimate.
        initial_cov: ``(n, n)`` initial covariance (symmetric PSD).
        decision: the fault declaration rule.
        gate: chi-square gate on the normalised innovation squared, or ``None``.
    """

    method: str
    transition: np.ndarray | None = None
    stay: float | None = None
    initial_mode_probs: np.ndarray | None = None
    initial_mean: np.ndarray
    initial_cov: np.ndarray
    decision: DecisionSpec = DecisionSpec()
    gate: float | None = None


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Scenario:
    """One validated experiment.

    Build it with :func:`load_scenario` or :func:`parse_scenario`; constructing it by
    hand (or with :func:`dataclasses.replace`) skips validation -- run the result through
    ``parse_scenario(scenario_to_dict(s))`` to check it.

    Attributes:
        name: label used in outputs.
        duration: simulated time, s.
        dt: sample time, s.
        seed: random seed (>= 0) for the noise.
        plant: the registered plant object.
        plant_params: overrides of the plant's nominal parameters, by name.
        input: the input signal.
        process_noise: ``(n, n)`` process noise covariance Q.
        measurement_noise: ``(m, m)`` measurement noise covariance R.
        faults: the scenario's fault library, in order: fault name -> {parameter: fault
            value}.  Model ``j`` (1-based among the faults) of the UIMM bank is fault ``j-1``.
        events: the true fault events, sorted by time.
        filter: the filter-bank settings.
        sweep: the raw ``[sweep]`` table (validated by the module that uses it), or ``None``.
        source: where the scenario came from (a file name or ``"<dict>"``).
    """

    name: str
    duration: float
    dt: float
    seed: int = 0
    plant: Plant
    plant_params: dict[str, float]
    input: InputSpec
    process_noise: np.ndarray
    measurement_noise: np.ndarray
    faults: dict[str, dict[str, float]]
    events: tuple[EventSpec, ...] = ()
    filter: FilterSpec
    sweep: dict[str, Any] | None = None
    source: str = "<dict>"

    @property
    def num_steps(self) -> int:
        """Number of samples, ``round(duration / dt)``."""
        return int(round(self.duration / self.dt))

    @property
    def fault_names(self) -> tuple[str, ...]:
        """Names of the library's faults, in order."""
        return tuple(self.faults)

    @property
    def num_faults(self) -> int:
        """Number of faults ``F`` in the library."""
        return len(self.faults)

    @property
    def nominal_params(self) -> dict[str, float]:
        """The plant's nominal parameters with ``plant_params`` applied."""
        params = {k: float(v) for k, v in self.plant.nominal.items()}
        params.update(self.plant_params)
        return params

    def num_models(self, method: str | None = None) -> int:
        """Number of models of the bank: ``F + 1`` for ``"uimm"``, ``2**F`` for ``"imm"``.

        Args:
            method: ``"uimm"`` or ``"imm"``; default: ``filter.method``.
        """
        return _num_models(method or self.filter.method, self.num_faults)

    def transition_matrix(self, method: str | None = None) -> np.ndarray:
        """The ``(M, M)`` transition matrix (``filter.transition``, or built from ``stay``).

        With ``stay = s`` the diagonal is ``s`` and every off-diagonal entry of a row is
        ``(1 - s) / (M - 1)``.

        Args:
            method: ``"uimm"`` or ``"imm"``; default: ``filter.method``.  A matrix given in
                full can only be used for the method it was written for.

        Returns:
            A new float64 array.
        """
        method = method or self.filter.method
        size = self.num_models(method)
        if self.filter.transition is not None:
            if method != self.filter.method:
                raise ValueError(
                    f"scenario {self.name!r} gives [filter].transition in full for method "
                    f"{self.filter.method!r}; it cannot be used for method {method!r} "
                    f"({size} models). Give stay instead."
                )
            return np.array(self.filter.transition, dtype=np.float64)
        if size == 1:
            return np.ones((1, 1))
        stay = float(self.filter.stay)  # type: ignore[arg-type]
        matrix = np.full((size, size), (1.0 - stay) / (size - 1))
        np.fill_diagonal(matrix, stay)
        return matrix

    def initial_mode_probs(self, method: str | None = None) -> np.ndarray:
        """The ``(M,)`` initial mode probabilities (given, or the default).

        The default puts :data:`DEFAULT_NOMINAL_PROB` (0.9) on model 0 and shares the
        remaining 0.1 equally among the other models.

        Args:
            method: ``"uimm"`` or ``"imm"``; default: ``filter.method``.

        Returns:
            A new float64 array summing to 1.
        """
        method = method or self.filter.method
        size = self.num_models(method)
        if self.filter.initial_mode_probs is not None:
            if method != self.filter.method:
                raise ValueError(
                    f"scenario {self.name!r} gives [filter].initial_mode_probs for method "
                    f"{self.filter.method!r}; it cannot be used for method {method!r}."
                )
            return np.array(self.filter.initial_mode_probs, dtype=np.float64)
        return _default_mode_probs(size)


def _num_models(method: str, num_faults: int) -> int:
    if method == "uimm":
        return num_faults + 1
    if method == "imm":
        return 2**num_faults
    raise ValueError(f"unknown method {method!r}; expected one of {METHODS}")


def _default_mode_probs(size: int) -> np.ndarray:
    if size == 1:
        return np.ones(1)
    probs = np.full(size, (1.0 - DEFAULT_NOMINAL_PROB) / (size - 1))
    probs[0] = DEFAULT_NOMINAL_PROB
    return probs


# --------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------


def load_scenario(path: str | os.PathLike[str]) -> Scenario:
    """Read and validate a scenario file.

    Args:
        path: a ``.toml`` file following ``docs/scenarios.md``.

    Returns:
        The validated :class:`Scenario`.

    Raises:
        ScenarioError: the file is missing, is not valid TOML, or breaks the schema.
    """
    if not isinstance(path, str | os.PathLike):
        raise TypeError(
            f"load_scenario: path: expected the path of a .toml scenario file (str or "
            f"pathlib.Path), got {type(path).__name__} {path!r}"
        )
    path = Path(path)
    source = str(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        hint = ""
        if path.parent.is_dir():
            names = [p.name for p in path.parent.glob("*.toml")]
            close = difflib.get_close_matches(path.name, names, n=1)
            if close:
                hint = f" Did you mean {str(path.parent / close[0])!r}?"
        raise ScenarioError(
            f"scenario file not found (working directory: {os.getcwd()}).{hint}",
            source=source,
        ) from None
    except IsADirectoryError:
        raise ScenarioError(
            "is a directory; give the path of a .toml scenario file", source=source
        ) from None
    try:
        data = tomllib.loads(raw.decode("utf-8-sig"))  # a byte-order mark is tolerated
    except UnicodeDecodeError as exc:
        raise ScenarioError(f"the file is not UTF-8 text ({exc})", source=source) from None
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(
            f"TOML syntax error: {exc}. See https://toml.io for the syntax.", source=source
        ) from None
    scenario, notes = _Parser(source).parse(data)
    for note in notes:
        warnings.warn(note, UIMMWarning, stacklevel=2)
    return scenario


def nonpositive_param(
    plant: Plant, nominal: Mapping[str, float], values: Mapping[str, float], magnitude: float
) -> tuple[str, float] | None:
    """The first of the plant's ``positive_params`` that a fault event takes to ``<= 0``.

    At magnitude ``a`` a parameter of the fault takes ``nominal + a (fault_value - nominal)``
    in the truth.  Returns ``(name, value)``, or ``None`` if every one stays positive.
    """
    for key, fv in values.items():
        value = nominal[key] + magnitude * (fv - nominal[key])
        if key in plant.positive_params and not value > 0:
            return key, value
    return None


def parse_scenario(data: Mapping[str, Any], source: str = "<dict>") -> Scenario:
    """Validate a scenario given as a dict (the structure of the TOML file).

    Lists, tuples, NumPy arrays and NumPy scalars are all accepted where the TOML file
    has arrays and numbers.

    Args:
        data: the scenario, e.g. ``tomllib.load(f)`` or :func:`scenario_to_dict` output.
        source: name used in error messages.

    Returns:
        The validated :class:`Scenario`.

    Raises:
        ScenarioError: the dict breaks the schema.
    """
    scenario, notes = _Parser(source).parse(data)
    for note in notes:
        warnings.warn(note, UIMMWarning, stacklevel=2)
    return scenario


_TOP_KEYS = (
    "name",
    "duration",
    "dt",
    "seed",
    "plant",
    "input",
    "noise",
    "faults",
    "events",
    "filter",
    "sweep",
)
_PLANT_KEYS = ("model", "params")
_INPUT_KEYS = ("kind", "amplitude", "frequency", "offset", "step_time")
_NOISE_KEYS = ("process", "measurement")
_EVENT_KEYS = ("time", "fault", "magnitude")
_FILTER_KEYS = (
    "method",
    "stay",
    "transition",
    "initial_mode_probs",
    "initial_mean",
    "initial_cov",
    "gate",
    "decision",
)
_DECISION_KEYS = ("threshold", "hold")

_HINTS = {
    "name": 'a label for outputs, e.g. name = "paper-sim1"',
    "duration": "the simulated time in seconds, e.g. duration = 100.0",
    "dt": "the sample time in seconds, e.g. dt = 1.0e-4",
    "plant": '[plant] with model = "hydraulic_actuator" (a registered plant name)',
    "model": 'a registered plant name, e.g. model = "hydraulic_actuator"',
    "input": '[input] with kind = "sine" and amplitude = 0.01',
    "kind": f"one of {', '.join(INPUT_KINDS)}",
    "amplitude": "the signal amplitude in input units, e.g. amplitude = 0.01",
    "noise": "[noise] with process = [...] and measurement = [...]",
    "process": "the diagonal of Q (one entry per state) or the full n x n matrix",
    "measurement": "the diagonal of R (one entry per output) or the full m x m matrix",
    "filter": '[filter] with method = "uimm" and stay = 0.999 (or transition = [[...]])',
    "method": f"one of {', '.join(METHODS)}",
    "time": "the fault onset in seconds",
    "fault": "the name of a fault of the [faults] library",
}


def _type_name(value: Any) -> str:
    if isinstance(value, bool):
        return f"a boolean ({str(value).lower()})"
    if isinstance(value, str):
        return f"a string ({value!r})"
    if isinstance(value, int):
        return f"an integer ({value})"
    if isinstance(value, float):
        return f"a float ({value!r})"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, Mapping):
        return "a table"
    if isinstance(value, datetime.date | datetime.time):
        return f"a date/time ({value.isoformat()})"
    return f"a {type(value).__name__}"


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _suggest(word: str, choices: Iterable[str]) -> str:
    choices = list(choices)
    lowered = {c.lower(): c for c in choices}
    close = difflib.get_close_matches(word.lower(), list(lowered), n=1, cutoff=0.6)
    return f" Did you mean {lowered[close[0]]!r}?" if close else ""


def _plain(value: Any, where: str, source: str) -> Any:
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
            out[k] = _plain(v, f"{where}.{k}" if where else k, source)
        return out
    if isinstance(value, np.ndarray):
        return _plain(value.tolist(), where, source)
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, list | tuple):
        return [_plain(v, where, source) for v in value]
    return value


def _key(name: str) -> str:
    """A TOML key: bare if possible, else a quoted basic string."""
    return name if re.fullmatch(r"[A-Za-z0-9_-]+", name) else _toml_string(name)


class _Parser:
    """Validates one scenario dict; collects warnings to be emitted by the caller."""

    def __init__(self, source: str):
        self.source = source
        self.notes: list[str] = []

    # -- error helpers ------------------------------------------------------------------

    def fail(self, field: str | None, detail: str) -> NoReturn:
        raise ScenarioError(detail, source=self.source, field=field)

    def warn(self, field: str, detail: str) -> None:
        self.notes.append(f"{self.source}: {field}: {detail}")

    @staticmethod
    def path(header: str, key: str) -> str:
        return f"{header}.{_key(key)}" if header else _key(key)

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
                    f"unknown key {key!r} in {where}.{_suggest(key, allowed)} "
                    f"Allowed keys: {', '.join(allowed)}.",
                )
        for key in required:
            if key not in table:
                hint = _HINTS.get(key, "")
                self.fail(
                    self.path(header, key),
                    f"required key is missing from {where}" + (f"; give {hint}." if hint else "."),
                )

    def table(self, value: Any, field: str, what: str = "") -> Mapping[str, Any]:
        if not isinstance(value, Mapping):
            hint = ""
            if field.startswith("[") and not field.startswith("[["):
                hint = f" Write it as a {field} section (or an inline table {{...}})."
            self.fail(field, f"must be a table{what}, got {_type_name(value)}.{hint}")
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
        if not _is_number(value):
            self.fail(field, f"must be a number{unit_txt}, got {_type_name(value)}.")
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
        rng = f">= {low}" if high is None else f"in [{low}, {high}]"
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            self.fail(field, f"must be an integer {rng}, got {_type_name(value)}.")
        if int(value) < low or (high is not None and int(value) > high):
            self.fail(field, f"must be an integer {rng}, got {int(value)}.")
        return int(value)

    def string(self, value: Any, field: str) -> str:
        if not isinstance(value, str):
            self.fail(field, f"must be a string, got {_type_name(value)}.")
        if not value.strip():
            self.fail(field, "must be a non-empty string.")
        return value

    def vector(self, value: Any, field: str, length: int, what: str) -> np.ndarray:
        if not isinstance(value, list):
            self.fail(
                field, f"must be an array of {length} numbers ({what}), got {_type_name(value)}."
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
        if _is_number(value):
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
                f"{symbol}) or a {size} x {size} matrix, got {_type_name(value)}.",
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

    # -- the schema ---------------------------------------------------------------------

    def parse(self, data: Mapping[str, Any]) -> tuple[Scenario, list[str]]:
        top = self.table(_plain(data, "", self.source), "top level")
        self.keys(top, "", _TOP_KEYS, ("name", "duration", "dt"))
        for table in ("plant", "input", "noise", "filter"):
            if table not in top:
                self.fail(f"[{table}]", f"required table is missing; add {_HINTS[table]}.")

        name = self.string(top["name"], "name")
        duration = self.number(top["duration"], "duration", low=0.0, low_open=True, unit="(s)")
        dt = self.number(top["dt"], "dt", low=0.0, low_open=True, unit="(s)")
        if dt > duration:
            self.fail("dt", f"the sample time {dt!r} s is longer than duration = {duration!r} s.")
        ratio = duration / dt
        if abs(ratio - round(ratio)) > 1e-9 * max(1.0, ratio):
            self.fail(
                "dt",
                f"duration / dt = {duration!r} / {dt!r} = {ratio!r} is not an integer number "
                "of samples; choose dt so that it divides duration.",
            )
        if round(ratio) > MAX_INT32:
            self.fail(
                "duration",
                f"duration / dt = {ratio:.4g} samples; a run holds at most {MAX_INT32} "
                "(the step counter is int32, and every sample's outputs are kept): shorten "
                "duration or lengthen dt.",
            )
        seed = self.integer(top.get("seed", 0), "seed", low=0, high=MAX_SEED)

        plant, plant_params = self.parse_plant(top["plant"])
        nominal = {k: float(v) for k, v in plant.nominal.items()}
        nominal.update(plant_params)
        input_spec = self.parse_input(top["input"])
        self.check_input_timing(input_spec, duration, dt)
        process, measurement = self.parse_noise(top["noise"], plant)
        faults = self.parse_faults(top.get("faults"), plant, nominal)
        events = self.parse_events(top.get("events"), faults, duration, dt, plant, nominal)
        filter_spec = self.parse_filter(top["filter"], plant, len(faults))
        sweep = None
        if "sweep" in top:
            sweep = copy.deepcopy(dict(self.table(top["sweep"], "[sweep]")))
            self.writable(sweep, "[sweep]")

        scenario = Scenario(
            name=name,
            duration=duration,
            dt=dt,
            seed=seed,
            plant=plant,
            plant_params=plant_params,
            input=input_spec,
            process_noise=_frozen(process),
            measurement_noise=_frozen(measurement),
            faults=faults,
            events=events,
            filter=filter_spec,
            sweep=sweep,
            source=self.source,
        )
        return scenario, self.notes

    def writable(self, value: Any, field: str) -> None:
        """Check that a raw value (the ``[sweep]`` table) holds only TOML types."""
        if isinstance(value, Mapping):
            for k, v in value.items():
                self.writable(v, f"{field}.{_key(k)}")
        elif isinstance(value, list):
            for i, v in enumerate(value):
                self.writable(v, f"{field}[{i}]")
        elif not isinstance(value, str | numbers.Real | datetime.date | datetime.time):
            self.fail(
                field,
                f"{_type_name(value)} cannot be written to TOML; use strings, numbers, "
                "booleans, dates, arrays and tables only.",
            )

    def parse_plant(self, value: Any) -> tuple[Plant, dict[str, float]]:
        table = self.table(value, "[plant]")
        self.keys(table, "[plant]", _PLANT_KEYS, ("model",))
        model = self.string(table["model"], "[plant].model")
        try:
            plant = get_plant(model)
        except ValueError:
            known = list_plants()
            self.fail(
                "[plant].model",
                f"unknown plant model {model!r}.{_suggest(model, known)} Registered models: "
                f"{', '.join(known)} (register your own with uimm_jax.register_plant()).",
            )
        params: dict[str, float] = {}
        if "params" in table:
            ptable = self.table(table["params"], "[plant.params]")
            for key, v in ptable.items():
                field = self.path("[plant.params]", key)
                self.param_name(key, field, plant)
                params[key] = self.positive(plant, key, self.number(v, field), field)
        return plant, params

    def positive(self, plant: Plant, key: str, value: float, field: str) -> float:
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
                f"{_suggest(key, plant.param_names)} Known parameters: "
                f"{', '.join(plant.param_names)}.",
            )

    def parse_input(self, value: Any) -> InputSpec:
        table = self.table(value, "[input]")
        self.keys(table, "[input]", _INPUT_KEYS, ("kind", "amplitude"))
        kind = self.string(table["kind"], "[input].kind")
        if kind not in INPUT_KINDS:
            self.fail(
                "[input].kind",
                f"unknown input kind {kind!r}.{_suggest(kind, INPUT_KINDS)} Expected one of: "
                f"{', '.join(INPUT_KINDS)}.",
            )
        amplitude = self.number(table["amplitude"], "[input].amplitude")
        offset = self.number(table.get("offset", 0.0), "[input].offset")
        frequency = 1.0
        if "frequency" in table:
            if kind not in ("sine", "square"):
                self.fail(
                    "[input].frequency",
                    f"frequency applies to kind = 'sine' or 'square' only, not {kind!r}; "
                    "remove it.",
                )
            frequency = self.number(
                table["frequency"], "[input].frequency", low=0.0, low_open=True, unit="(Hz)"
            )
        step_time = 0.0
        if "step_time" in table:
            if kind != "step":
                self.fail(
                    "[input].step_time",
                    f"step_time applies to kind = 'step' only, not {kind!r}; remove it.",
                )
            step_time = self.number(table["step_time"], "[input].step_time", low=0.0, unit="(s)")
        return InputSpec(kind, amplitude, frequency, offset, step_time)

    def check_input_timing(self, spec: InputSpec, duration: float, dt: float) -> None:
        """Warn about inputs that the sampled run cannot show (accepted, not changed)."""
        nyquist = 0.5 / dt
        if spec.kind in ("sine", "square") and spec.frequency >= nyquist:
            self.warn(
                "[input].frequency",
                f"{spec.frequency!r} Hz is at or above the Nyquist frequency 1 / (2 dt) = "
                f"{nyquist!r} Hz: the sampled input aliases (a sine at exactly Nyquist is "
                "sampled at its zeros, i.e. no excitation).",
            )
        if spec.kind == "step" and spec.step_time >= duration:
            self.warn(
                "[input].step_time",
                f"{spec.step_time!r} s is not before duration = {duration!r} s: the step "
                "never happens in this run.",
            )

    def parse_noise(self, value: Any, plant: Plant) -> tuple[np.ndarray, np.ndarray]:
        table = self.table(value, "[noise]")
        self.keys(table, "[noise]", _NOISE_KEYS, _NOISE_KEYS)
        process = self.covariance(
            table["process"], "[noise].process", plant.state_names, definite=False, symbol="Q"
        )
        measurement = self.covariance(
            table["measurement"],
            "[noise].measurement",
            plant.output_names,
            definite=True,
            symbol="R",
        )
        return process, measurement

    def parse_faults(
        self, value: Any, plant: Plant, nominal: Mapping[str, float]
    ) -> dict[str, dict[str, float]]:
        if value is None:
            if not plant.faults:
                self.fail(
                    "[faults]",
                    f"plant {plant.name!r} has no default fault library; define the faults "
                    "with [faults.<name>] tables (parameter = fault value).",
                )
            return {f.name: {k: float(v) for k, v in f.values.items()} for f in plant.faults}
        table = self.table(value, "[faults]")
        if not table:
            self.fail(
                "[faults]",
                "defines no fault; add [faults.<name>] tables (parameter = fault value), or "
                "remove [faults] to use the plant's default library "
                f"({', '.join(f.name for f in plant.faults) or 'none'}).",
            )
        library = plant.fault_library
        faults: dict[str, dict[str, float]] = {}
        owner: dict[str, str] = {}
        for fname, ftable in table.items():
            header = f"[faults.{_key(fname)}]"
            ftable = self.table(ftable, header, " of parameter = fault value")
            if not ftable:
                if fname not in library:
                    self.fail(
                        header,
                        f"empty fault table, and {fname!r} is not in the fault library of "
                        f"plant {plant.name!r}.{_suggest(fname, library)} Either give its "
                        "parameters (parameter = fault value) or use a library fault: "
                        f"{', '.join(library)}.",
                    )
                values = {k: float(v) for k, v in library[fname].values.items()}
            else:
                values = {}
                for key, v in ftable.items():
                    field = self.path(header, key)
                    self.param_name(key, field, plant)
                    values[key] = self.positive(plant, key, self.number(v, field), field)
            for key, v in values.items():
                field = self.path(header, key)
                if key in owner:
                    self.fail(
                        field,
                        f"faults {owner[key]!r} and {fname!r} both change parameter {key!r}; "
                        "overlapping faults are not supported (each parameter may belong to "
                        "one fault of the library only). Merge them or drop one.",
                    )
                owner[key] = fname
                if v == nominal[key]:
                    self.warn(
                        field,
                        f"fault {fname!r} sets {key} = {v!r}, its nominal value: this "
                        "parameter does not change when the fault occurs.",
                    )
            faults[fname] = values
        return faults

    def parse_events(
        self,
        value: Any,
        faults: Mapping[str, Any],
        duration: float,
        dt: float,
        plant: Plant,
        nominal: Mapping[str, float],
    ) -> tuple[EventSpec, ...]:
        if value is None:
            return ()
        if not isinstance(value, list) or not all(isinstance(e, Mapping) for e in value):
            self.fail(
                "[[events]]",
                f"must be an array of tables (one [[events]] section per fault onset), got "
                f"{_type_name(value)}.",
            )
        events = []
        first: dict[str, int] = {}
        onset: dict[int, int] = {}
        num_steps = int(round(duration / dt))
        for i, entry in enumerate(value):
            header = f"[[events]][{i}]"
            self.keys(entry, header, _EVENT_KEYS, ("time", "fault"))
            time = self.number(
                entry["time"],
                f"{header}.time",
                low=0.0,
                high=duration,
                high_open=True,
                unit="(s; an onset in [0, duration))",
            )
            step = int(round(time / dt))  # the sample the fault acts from (runner.py)
            if step >= num_steps:
                self.fail(
                    f"{header}.time",
                    f"{time!r} s acts from sample round(time / dt) = {step}, but the run's "
                    f"samples are 0..{num_steps - 1}: the fault would never occur. Move the "
                    f"onset before {(num_steps - 0.5) * dt!r} s.",
                )
            fault = self.string(entry["fault"], f"{header}.fault")
            if fault not in faults:
                extra = ""
                if fault in plant.fault_library:
                    extra = (
                        f" {fault!r} is in the plant's fault library: add an empty "
                        f"[faults.{_key(fault)}] table to diagnose it."
                    )
                self.fail(
                    f"{header}.fault",
                    f"unknown fault {fault!r}: not in this scenario's fault library "
                    f"({', '.join(faults)}).{_suggest(fault, faults)}{extra}",
                )
            if fault in first:
                self.fail(
                    f"{header}.fault",
                    f"fault {fault!r} already occurs in [[events]][{first[fault]}]; faults are "
                    "irreversible, so each fault may occur once.",
                )
            first[fault] = i
            magnitude = self.number(
                entry.get("magnitude", 1.0), f"{header}.magnitude", low=0.0, low_open=True
            )
            bad = nonpositive_param(plant, nominal, faults[fault], magnitude)
            if bad:
                key, value = bad
                self.fail(
                    f"{header}.magnitude",
                    f"{magnitude!r} takes {key} from {nominal[key]!r} to {value!r} (the fault "
                    f"value {faults[fault][key]!r} at magnitude 1), but {key} must stay > 0.",
                )
            if step in onset:
                self.warn(
                    f"{header}.time",
                    f"fault {fault!r} starts on the same sample ({step}) as "
                    f"[[events]][{onset[step]}]: a UIMM bank (declared set + one fault) cannot "
                    "represent two faults appearing together; it may declare them one after "
                    "the other, or not at all (README, Known limitations).",
                )
            onset.setdefault(step, i)
            events.append(EventSpec(time, fault, magnitude))
        return tuple(sorted(events, key=lambda e: e.time))

    def parse_filter(self, value: Any, plant: Plant, num_faults: int) -> FilterSpec:
        table = self.table(value, "[filter]")
        self.keys(table, "[filter]", _FILTER_KEYS, ("method",))
        method = self.string(table["method"], "[filter].method")
        if method not in METHODS:
            self.fail(
                "[filter].method",
                f"unknown method {method!r}.{_suggest(method, METHODS)} Expected one of: "
                f"{', '.join(METHODS)}.",
            )
        size = _num_models(method, num_faults)
        models = (
            f"method {method!r} with {num_faults} faults has "
            + (f"F + 1 = {size}" if method == "uimm" else f"2**F = {size}")
            + " models"
        )

        transition = stay = None
        if "stay" in table and "transition" in table:
            self.fail("[filter].stay", "give either stay or transition, not both.")
        if "stay" in table:
            stay = self.number(
                table["stay"], "[filter].stay", low=0.0, high=1.0, low_open=True, high_open=True
            )
        elif "transition" in table:
            transition = self.matrix(table["transition"], "[filter].transition", size, models)
            for i, row in enumerate(transition):
                for j, p in enumerate(row):
                    if p < 0.0:
                        self.fail(
                            f"[filter].transition[{i}][{j}]",
                            f"transition probabilities must be >= 0, got {float(p)!r}.",
                        )
                total = float(np.sum(row))
                if abs(total - 1.0) > ROW_SUM_TOL:
                    self.fail(
                        "[filter].transition",
                        f"row {i} (from model {i}) sums to {total:.12g}; every row must sum to 1 "
                        f"within {ROW_SUM_TOL} (rows are not normalised for you).",
                    )
            transition = _frozen(transition)
        else:
            self.fail(
                "[filter].stay",
                "[filter] needs one of stay (self-transition probability in (0, 1), e.g. "
                f"stay = 0.999) or transition (the full {size} x {size} matrix; {models}).",
            )

        probs = None
        if "initial_mode_probs" in table:
            field = "[filter].initial_mode_probs"
            probs = self.vector(table["initial_mode_probs"], field, size, models)
            for i, p in enumerate(probs):
                if p < 0.0:
                    self.fail(f"{field}[{i}]", f"probabilities must be >= 0, got {float(p)!r}.")
            with np.errstate(over="ignore"):  # an overflowing sum is refused below
                total = float(np.sum(probs))
            if total <= 0.0:
                self.fail(field, "all probabilities are zero; at least one must be > 0.")
            if not np.isfinite(total):
                self.fail(
                    field,
                    f"the entries sum to {total!r} (overflow); give probabilities (numbers in "
                    "[0, 1], normalised with a warning if they do not sum to 1).",
                )
            if abs(total - 1.0) > PROB_SUM_TOL:
                probs = probs / total
                self.warn(
                    field,
                    f"the initial mode probabilities sum to {total!r}, not 1: normalised to "
                    f"{[float(p) for p in probs]}.",
                )
            probs = _frozen(probs)

        n = plant.state_dim
        states = f"one per state: {', '.join(plant.state_names)}"
        if "initial_mean" in table:
            mean = self.vector(table["initial_mean"], "[filter].initial_mean", n, states)
        else:
            mean = np.zeros(n)
        cov = self.covariance(
            table.get("initial_cov", DEFAULT_INITIAL_COV),
            "[filter].initial_cov",
            plant.state_names,
            definite=False,
            symbol="P0",
        )
        gate = None
        if "gate" in table:
            gate = self.number(table["gate"], "[filter].gate", low=0.0, low_open=True)

        decision = DecisionSpec()
        if "decision" in table:
            dtable = self.table(table["decision"], "[filter.decision]")
            self.keys(dtable, "[filter.decision]", _DECISION_KEYS)
            threshold = self.number(
                dtable.get("threshold", decision.threshold),
                "[filter.decision].threshold",
                low=0.0,
                high=1.0,
                low_open=True,
            )
            hold = self.integer(
                dtable.get("hold", decision.hold), "[filter.decision].hold", low=1, high=MAX_INT32
            )
            decision = DecisionSpec(threshold, hold)

        return FilterSpec(
            method=method,
            transition=transition,
            stay=stay,
            initial_mode_probs=probs,
            initial_mean=_frozen(mean),
            initial_cov=_frozen(cov),
            decision=decision,
            gate=gate,
        )


def _frozen(array: np.ndarray) -> np.ndarray:
    """A read-only float64 copy: scenarios are immutable."""
    out = np.array(array, dtype=np.float64)
    out.setflags(write=False)
    return out


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def _cov_to_toml(mat: np.ndarray) -> list[Any]:
    mat = np.asarray(mat, dtype=np.float64)
    if np.array_equal(mat, np.diag(np.diag(mat))):
        return [float(v) for v in np.diag(mat)]
    return [[float(v) for v in row] for row in mat]


def scenario_to_dict(scenario: Scenario) -> dict[str, Any]:
    """The TOML-shaped dict of a scenario (plain lists and floats).

    ``parse_scenario(scenario_to_dict(s))`` gives back ``s``.  Useful for building
    variants: edit the dict, then parse it again to validate.

    Args:
        scenario: a validated scenario.

    Returns:
        A new dict with the structure of the scenario file.
    """
    out: dict[str, Any] = {
        "name": scenario.name,
        "duration": float(scenario.duration),
        "dt": float(scenario.dt),
        "seed": int(scenario.seed),
    }
    plant: dict[str, Any] = {"model": scenario.plant.name}
    if scenario.plant_params:
        plant["params"] = {k: float(v) for k, v in scenario.plant_params.items()}
    out["plant"] = plant
    inp = scenario.input
    input_table: dict[str, Any] = {"kind": inp.kind, "amplitude": float(inp.amplitude)}
    if inp.kind in ("sine", "square"):
        input_table["frequency"] = float(inp.frequency)
    input_table["offset"] = float(inp.offset)
    if inp.kind == "step":
        input_table["step_time"] = float(inp.step_time)
    out["input"] = input_table
    out["noise"] = {
        "process": _cov_to_toml(scenario.process_noise),
        "measurement": _cov_to_toml(scenario.measurement_noise),
    }
    out["faults"] = {
        name: {k: float(v) for k, v in values.items()} for name, values in scenario.faults.items()
    }
    if scenario.events:
        out["events"] = [
            {"time": float(e.time), "fault": e.fault, "magnitude": float(e.magnitude)}
            for e in scenario.events
        ]
    flt = scenario.filter
    filter_table: dict[str, Any] = {"method": flt.method}
    if flt.transition is not None:
        filter_table["transition"] = [[float(v) for v in row] for row in flt.transition]
    else:
        filter_table["stay"] = float(flt.stay)  # type: ignore[arg-type]
    if flt.initial_mode_probs is not None:
        filter_table["initial_mode_probs"] = [float(v) for v in flt.initial_mode_probs]
    filter_table["initial_mean"] = [float(v) for v in flt.initial_mean]
    filter_table["initial_cov"] = _cov_to_toml(flt.initial_cov)
    if flt.gate is not None:
        filter_table["gate"] = float(flt.gate)
    filter_table["decision"] = {
        "threshold": float(flt.decision.threshold),
        "hold": int(flt.decision.hold),
    }
    out["filter"] = filter_table
    if scenario.sweep is not None:
        out["sweep"] = copy.deepcopy(scenario.sweep)
    return out


def scenario_to_toml(scenario: Scenario | Mapping[str, Any]) -> str:
    """Write a scenario as TOML text that :func:`load_scenario` reads back exactly.

    Floats are written with ``repr`` (shortest round-trip form), so
    ``load(dump(s))`` equals ``s`` field by field (``source`` aside).  Covariances
    that are diagonal are written as their diagonal.

    Args:
        scenario: a :class:`Scenario`, or a scenario dict (validated first with
            :func:`parse_scenario`, so the text is always a valid scenario).

    Returns:
        The TOML document.
    """
    if not isinstance(scenario, Scenario):
        scenario, notes = _Parser("<dict>").parse(scenario)
        for note in notes:
            warnings.warn(note, UIMMWarning, stacklevel=2)
    header = (
        f"# Scenario {scenario.name!r}, written by uimm_jax.scenarios.scenario_to_toml.\n"
        "# Schema: docs/scenarios.md\n"
    )
    return header + _dumps_document(scenario_to_dict(scenario))


def dump_scenario(scenario: Scenario | Mapping[str, Any], path: str | os.PathLike[str]) -> Path:
    """Write a scenario file (see :func:`scenario_to_toml`).

    Args:
        scenario: a :class:`Scenario` or a scenario dict.
        path: destination ``.toml`` file; its parent directory must exist.

    Returns:
        The path written.
    """
    path = Path(path)
    if not isinstance(scenario, Scenario):
        scenario, notes = _Parser("<dict>").parse(scenario)
        for note in notes:
            warnings.warn(note, UIMMWarning, stacklevel=2)
    path.write_text(scenario_to_toml(scenario), encoding="utf-8")
    return path


# -- a small general TOML writer (tables, arrays of tables, inline values) -------------

_ESCAPES = {
    '"': '\\"',
    "\\": "\\\\",
    "\b": "\\b",
    "\t": "\\t",
    "\n": "\\n",
    "\f": "\\f",
    "\r": "\\r",
}


def _toml_string(text: str) -> str:
    out = []
    for ch in text:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml_float(x: float) -> str:
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return repr(float(x))


def _toml_value(value: Any, indent: str = "") -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        return _toml_float(float(value))
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, datetime.date | datetime.time):
        return value.isoformat()
    if isinstance(value, Mapping):
        items = ", ".join(f"{_key(k)} = {_toml_value(v)}" for k, v in value.items())
        return "{ " + items + " }" if items else "{}"
    if isinstance(value, list | tuple):
        if value and all(isinstance(v, list | tuple) for v in value):
            inner = indent + "  "
            rows = ",\n".join(inner + _toml_value(v, inner) for v in value)
            return "[\n" + rows + ",\n" + indent + "]"
        return "[" + ", ".join(_toml_value(v, indent) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML: {value!r}")


def _is_table_array(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, Mapping) for v in value)


def _dumps_document(doc: Mapping[str, Any]) -> str:
    lines: list[str] = []
    _emit_table(lines, [], doc, array_item=False)
    return "\n".join(lines).strip("\n") + "\n"


def _emit_table(
    lines: list[str], path: list[str], table: Mapping[str, Any], array_item: bool
) -> None:
    plain = {
        k: v for k, v in table.items() if not isinstance(v, Mapping) and not _is_table_array(v)
    }
    nested = {k: v for k, v in table.items() if k not in plain}
    dotted = ".".join(_key(p) for p in path)
    if array_item:
        lines += ["", f"[[{dotted}]]"]
    elif path and (plain or not nested):
        lines += ["", f"[{dotted}]"]
    for key, value in plain.items():
        lines.append(f"{_key(key)} = {_toml_value(value)}")
    for key, value in nested.items():
        if isinstance(value, Mapping):
            _emit_table(lines, [*path, key], value, array_item=False)
        else:
            for item in value:
                _emit_table(lines, [*path, key], item, array_item=True)
