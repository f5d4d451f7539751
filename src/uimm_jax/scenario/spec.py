"""The scenario of one experiment as validated data: :class:`Scenario` and its parts.

A scenario fixes everything a run needs: the plant and its parameter overrides, the input
signal, the noise covariances, the fault library (which faults the bank can diagnose),
the true fault events, and the filter settings (method, transition matrix or
self-transition probability, initial mode probabilities and state, decision rule).
The schema is documented key by key in ``docs/scenarios.md``; :mod:`uimm_jax.scenario.parse`
reads it, :mod:`uimm_jax.scenario.write` writes it back.

This module is pure Python/NumPy; it imports no JAX.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from uimm_jax._checks import ROW_SUM_TOL
from uimm_jax.engine.bank import param_at_magnitude
from uimm_jax.engine.truth import INPUT_KINDS
from uimm_jax.engine.uimm_est_types import EstSettings
from uimm_jax.plants.base import Plant

__all__ = [
    "DEFAULT_INITIAL_COV",
    "DEFAULT_NOMINAL_PROB",
    "INPUT_KINDS",
    "METHODS",
    "PROB_SUM_TOL",
    "PSD_RTOL",
    "ROW_SUM_TOL",
    "SYMMETRY_RTOL",
    "DecisionSpec",
    "EventSpec",
    "FilterSpec",
    "InputSpec",
    "Scenario",
    "nonpositive_param",
    "same_bank",
]

METHODS = ("uimm", "imm", "uimm-est")
"""Filter-bank methods: the updated IMM (F + 1 models) or the combinatorial IMM (2**F)."""

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
    """A true fault event: from ``time`` on, ``fault`` is present (until ``end``, if given).

    Attributes:
        time: s, in ``[0, duration)``.
        fault: name of a fault of the scenario's library.
        magnitude: the fault's size, any value > 0; 1 is the library's fault
            (:func:`~uimm_jax.engine.bank.param_at_magnitude`: ``nominal + magnitude *
            (fault_value - nominal)``, or ``nominal * (fault_value / nominal)^magnitude``
            for the plant's positive parameters).
        ramp: s; the magnitude grows linearly from 0 at ``time`` to ``magnitude`` at
            ``time + ramp`` (0: abrupt); with ``growth = "exponential"``, the time
            constant ``tau`` of ``magnitude (1 - exp(-(t - time) / tau))``.
        end: s or ``None``; from ``end`` on the fault is gone (intermittent or repaired).
        growth: ``"linear"`` or ``"exponential"``
            (:data:`~uimm_jax.engine.truth.GROWTH_KINDS`): the shape of a ramp.
    """

    time: float
    fault: str
    magnitude: float = 1.0
    ramp: float = 0.0
    end: float | None = None
    growth: str = "linear"


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
        method: ``"uimm"`` (F + 1 models), ``"uimm-est"`` (the same bank, estimating the
            faults' sizes) or ``"imm"`` (2**F models).
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
        est: the ``[filter.est]`` settings of ``"uimm-est"``
            (:class:`~uimm_jax.engine.uimm_est_types.EstSettings`, the keys not given at
            their defaults), or ``None`` when the table is absent (the defaults).
    """

    method: str
    transition: np.ndarray | None = None
    stay: float | None = None
    initial_mode_probs: np.ndarray | None = None
    initial_mean: np.ndarray
    initial_cov: np.ndarray
    decision: DecisionSpec = DecisionSpec()
    gate: float | None = None
    est: EstSettings | None = None


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
        plant_module: ``[plant].module`` resolved: the absolute path of the ``.py`` file
            or the module name imported before the plant was looked up, or ``None``.
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
    plant_module: str | None = None

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
            if not same_bank(method, self.filter.method):
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
            if not same_bank(method, self.filter.method):
                raise ValueError(
                    f"scenario {self.name!r} gives [filter].initial_mode_probs for method "
                    f"{self.filter.method!r}; it cannot be used for method {method!r}."
                )
            return np.array(self.filter.initial_mode_probs, dtype=np.float64)
        return _default_mode_probs(size)


def same_bank(a: str, b: str) -> bool:
    """True when methods ``a`` and ``b`` have the same bank layout.

    ``"uimm"`` and ``"uimm-est"`` both have ``F + 1`` models, model 0 the declared set and
    model ``j + 1`` fault ``j``'s hypothesis, so a transition matrix or initial mode
    probabilities written for one mean the same for the other.
    """
    return a == b or {a, b} <= {"uimm", "uimm-est"}


def _num_models(method: str, num_faults: int) -> int:
    if method in ("uimm", "uimm-est"):
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


def nonpositive_param(
    plant: Plant, nominal: Mapping[str, float], values: Mapping[str, float], magnitude: float
) -> tuple[str, float] | None:
    """The first of the plant's ``positive_params`` that a fault event takes to ``<= 0``.

    At magnitude ``a`` a parameter of the fault takes
    :func:`~uimm_jax.engine.bank.param_at_magnitude` in the truth (the log scale for
    ``positive_params``, which therefore stay positive whenever the fault value is).
    Returns ``(name, value)``, or ``None`` if every one stays positive.
    """
    for key, fv in values.items():
        log = key in plant.positive_params and nominal[key] > 0 and fv > 0
        value = float(param_at_magnitude(nominal[key], fv, magnitude, log, np))
        if key in plant.positive_params and not value > 0:
            return key, value
    return None
