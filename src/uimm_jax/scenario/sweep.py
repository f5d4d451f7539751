"""The ``[sweep]`` table of a scenario: its validated form (:class:`SweepSpec`).

:func:`sweep_spec` checks a scenario's ``[sweep]`` table (schema in ``docs/montecarlo.md``),
with keyword arguments overriding it, and returns a :class:`SweepSpec`; the Monte Carlo
runner (:mod:`uimm_jax.studies.sweep`) only reads that spec.  Errors are
:class:`~uimm_jax.errors.ScenarioError` naming the field (``[sweep].runs``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

from uimm_jax._checks import MAX_SEED, is_number
from uimm_jax.scenario._fields import FieldChecker
from uimm_jax.scenario.spec import METHODS, nonpositive_param

__all__ = [
    "DEFAULT_BATCH",
    "FAULT_FREE",
    "CaseSpec",
    "EventDraw",
    "SweepSpec",
    "sweep_spec",
]

FAULT_FREE = "fault-free"
"""Name of the fault-free case (reserved)."""

DEFAULT_BATCH = 128
"""Runs per compiled batch (see ``docs/montecarlo.md`` for the measured throughput)."""

_SWEEP_KEYS = (
    "runs",
    "seed",
    "methods",
    "magnitudes",
    "ramps",
    "noise_scales",
    "fault_free",
    "cases",
    "batch",
    "chunk",
)
_CASE_KEYS = ("name", "events")
_EVENT_KEYS = ("fault", "time", "magnitude", "ramp", "duration", "growth")


@dataclasses.dataclass(frozen=True)
class EventDraw:
    """One fault event of a case.

    Attributes:
        fault: a fault of the scenario's library.
        time: ``(lo, hi)`` onset window in s; ``lo == hi`` for a fixed onset.  A window's
            onset is drawn uniformly in ``[lo, hi)`` per run and rounded to a step.
        magnitude: the fault's size (before the cell's scale; 1 = the library's value,
            :func:`~uimm_jax.engine.bank.param_at_magnitude`).
        ramp: s, linear growth from nominal to the magnitude (0: abrupt); the time
            constant of an exponential ``growth``; a cell of the ``ramps`` axis replaces it.
        duration: ``(lo, hi)`` s the fault lasts, drawn uniformly per run (an intermittent
            fault), or ``None``: it stays.
        growth: the ramp's shape, ``"linear"`` or ``"exponential"``
            (:attr:`~uimm_jax.scenario.spec.EventSpec.growth`).
    """

    fault: str
    time: tuple[float, float]
    magnitude: float = 1.0
    ramp: float = 0.0
    duration: tuple[float, float] | None = None
    growth: str = "linear"


@dataclasses.dataclass(frozen=True)
class CaseSpec:
    """A named list of fault events (no event: fault-free).

    Attributes:
        name: the case's label.
        events: the events (each fault at most once).
    """

    name: str
    events: tuple[EventDraw, ...]


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """A validated sweep specification (see :func:`sweep_spec`).

    Attributes:
        runs: runs per cell.
        seed: root seed of the run keys.
        methods: methods to compare (``"uimm"``, ``"imm"``).
        magnitudes: scales of every event's magnitude.
        ramps: ramp lengths (s) that replace every event's ramp; ``(None,)``: the events'
            own ramps.
        noise_scales: scales of the truth's noise standard deviations.
        fault_free: include the fault-free case.
        cases: the fault cases.
        batch: runs per compiled batch.
        chunk: time steps per compiled chunk (``None``: about ``6.4e5 / batch``).
    """

    runs: int
    seed: int
    methods: tuple[str, ...]
    magnitudes: tuple[float, ...]
    noise_scales: tuple[float, ...]
    fault_free: bool
    cases: tuple[CaseSpec, ...]
    batch: int = DEFAULT_BATCH
    chunk: int | None = None
    ramps: tuple[float | None, ...] = (None,)


def _window(chk: FieldChecker, t: Any, field: str, what: str) -> tuple[float, float]:
    """A number or a window ``[lo, hi]`` (``lo <= hi``)."""
    if is_number(t):
        lo = hi = chk.number(t, field)
    elif isinstance(t, list | tuple) and len(t) == 2:
        lo = chk.number(t[0], f"{field}[0]")
        hi = chk.number(t[1], f"{field}[1]")
        if hi < lo:
            chk.fail(field, f"window [{lo!r}, {hi!r}] is reversed; write [lo, hi].")
    else:
        chk.fail(field, f"must be {what} in s or a window [lo, hi] to draw it from, got {t!r}.")
    return lo, hi


def _ramps(chk: FieldChecker, value: Any, field: str) -> tuple[float, ...]:
    """A number or a non-empty array of distinct finite numbers >= 0 (ramp lengths, s)."""
    if is_number(value):
        value = [value]
    if not isinstance(value, list | tuple) or not value:
        chk.fail(field, f"must be a non-empty array of ramp lengths >= 0 (s), got {value!r}.")
    out = tuple(chk.number(v, f"{field}[{i}]", low=0.0, unit="(s)") for i, v in enumerate(value))
    if len(set(out)) != len(out):
        chk.fail(field, f"has repeated values: {list(out)}.")
    return out


def _positive_numbers(chk: FieldChecker, value: Any, field: str) -> tuple[float, ...]:
    """A number or a non-empty array of distinct finite numbers > 0."""
    if is_number(value):
        value = [value]
    if not isinstance(value, list | tuple) or not value:
        chk.fail(field, f"must be a non-empty array of numbers > 0, got {value!r}.")
    out = tuple(chk.positive(v, f"{field}[{i}]") for i, v in enumerate(value))
    if len(set(out)) != len(out):
        chk.fail(field, f"has repeated values: {list(out)}.")
    return out


def _parse_event(
    chk: FieldChecker, entry: Any, field: str, scenario, ramp_axis: bool
) -> EventDraw:
    if not isinstance(entry, Mapping):
        chk.fail(field, f"must be a table {{fault = ..., time = ...}}, got {entry!r}.")
    chk.keys(entry, field, _EVENT_KEYS)
    for key in ("fault", "time"):
        if key not in entry:
            chk.fail(f"{field}.{key}", "required key is missing.")
    fault = entry["fault"]
    if fault not in scenario.faults:
        chk.fail(
            f"{field}.fault",
            f"unknown fault {fault!r}: not in the scenario's fault library "
            f"({', '.join(scenario.faults)}).",
        )
    t = entry["time"]
    dur = float(scenario.duration)
    lo, hi = _window(chk, t, f"{field}.time", "an onset time")
    if lo < 0 or hi >= dur:
        chk.fail(
            f"{field}.time",
            f"onset {t!r} s is outside the run [0, {dur!r}) s (duration of the scenario).",
        )
    chk.onset_step(lo, f"{field}.time", scenario.dt, scenario.num_steps)
    mag = chk.positive(entry.get("magnitude", 1.0), f"{field}.magnitude")
    ramp = chk.number(entry.get("ramp", 0.0), f"{field}.ramp", low=0.0, unit="(s)")
    duration = None
    if "duration" in entry:
        duration = _window(chk, entry["duration"], f"{field}.duration", "a duration")
        if duration[0] < float(scenario.dt):
            chk.fail(
                f"{field}.duration",
                f"{entry['duration']!r} s: a fault must last at least one sample "
                f"(dt = {float(scenario.dt)!r} s).",
            )
    growth = chk.growth(entry, field, ramp, ramp_axis)
    return EventDraw(str(fault), (lo, hi), mag, ramp, duration, growth)


def _parse_cases(
    chk: FieldChecker, value: Any, scenario, ramp_axis: bool
) -> tuple[CaseSpec, ...]:
    field = "[sweep].cases"
    if not isinstance(value, list | tuple):
        chk.fail(field, f"must be an array of tables ([[sweep.cases]]), got {value!r}.")
    cases = []
    names = set()
    for i, case in enumerate(value):
        cf = f"{field}[{i}]"
        if not isinstance(case, Mapping):
            chk.fail(cf, f"must be a table with name and events, got {case!r}.")
        chk.keys(case, cf, _CASE_KEYS)
        name = case.get("name", f"case{i}")
        if not isinstance(name, str) or not name.strip():
            chk.fail(f"{cf}.name", f"must be a non-empty string, got {name!r}.")
        if name == FAULT_FREE or name in names:
            chk.fail(
                f"{cf}.name",
                f"{name!r} is already used"
                + (" (reserved for the fault-free case)" if name == FAULT_FREE else "")
                + ".",
            )
        names.add(name)
        evs = case.get("events")
        if not isinstance(evs, list | tuple) or not evs:
            chk.fail(
                f"{cf}.events",
                "must be a non-empty array of events {fault, time[, magnitude]} (the "
                "fault-free case is added by fault_free = true).",
            )
        events = tuple(
            _parse_event(chk, e, f"{cf}.events[{j}]", scenario, ramp_axis)
            for j, e in enumerate(evs)
        )
        seen = [e.fault for e in events]
        dup = {f for f in seen if seen.count(f) > 1}
        if dup:
            chk.fail(
                f"{cf}.events",
                f"fault {sorted(dup)[0]!r} occurs twice; faults are irreversible, each may "
                "occur once per case.",
            )
        cases.append(CaseSpec(name, events))
    return tuple(cases)


def sweep_spec(
    scenario,
    *,
    runs: int | None = None,
    seed: int | None = None,
    methods: Sequence[str] | None = None,
    magnitudes: Sequence[float] | None = None,
    noise_scales: Sequence[float] | None = None,
    fault_free: bool | None = None,
    cases: Sequence[Mapping] | None = None,
    batch: int | None = None,
    chunk: int | None = None,
    ramps: Sequence[float] | None = None,
) -> SweepSpec:
    """Validate the scenario's ``[sweep]`` table, with the given arguments overriding it.

    Defaults: ``runs = 100``, ``seed`` = the scenario's seed, ``methods`` = the scenario's
    method, ``magnitudes = [1.0]``, ``noise_scales = [1.0]``, ``fault_free = true``,
    ``cases`` = one case named after the scenario with its ``[[events]]`` (none if it has
    no events), ``batch = 128``, ``chunk`` about ``6.4e5 / batch`` steps.

    Raises:
        ScenarioError: naming the field (``[sweep].runs``) and what is expected.
    """
    chk = FieldChecker(getattr(scenario, "source", None))
    table = scenario.sweep if scenario.sweep is not None else {}
    if not isinstance(table, Mapping):
        chk.fail("[sweep]", f"must be a table, got {table!r}.")
    chk.keys(table, "[sweep]", _SWEEP_KEYS)

    def pick(name, override):
        if override is not None:
            return override, name
        return table.get(name), f"[sweep].{name}"

    v, f = pick("runs", runs)
    runs_ = 100 if v is None else chk.integer(v, f, low=1)
    v, f = pick("seed", seed)
    seed_ = int(scenario.seed) if v is None else chk.integer(v, f, low=0, high=MAX_SEED)
    v, f = pick("methods", methods)
    if v is None:
        methods_ = (scenario.filter.method,)
    else:
        if isinstance(v, str):
            v = [v]
        if not isinstance(v, list | tuple) or not v:
            chk.fail(f, f"must be a non-empty array of {' / '.join(METHODS)}, got {v!r}.")
        for i, m in enumerate(v):
            if m not in METHODS:
                chk.fail(f"{f}[{i}]", f"must be one of {', '.join(METHODS)}, got {m!r}.")
        if len(set(v)) != len(v):
            chk.fail(f, f"has repeated methods: {list(v)}.")
        methods_ = tuple(v)
    v, f = pick("magnitudes", magnitudes)
    mags = (1.0,) if v is None else _positive_numbers(chk, list(v) if not is_number(v) else v, f)
    v, f = pick("ramps", ramps)
    ramps_ = (None,) if v is None else _ramps(chk, list(v) if not is_number(v) else v, f)
    v, f = pick("noise_scales", noise_scales)
    noises = (1.0,) if v is None else _positive_numbers(chk, list(v) if not is_number(v) else v, f)
    v, f = pick("fault_free", fault_free)
    ff = True if v is None else chk.boolean(v, f)
    v, f = pick("batch", batch)
    batch_ = DEFAULT_BATCH if v is None else chk.integer(v, f, low=1)
    v, f = pick("chunk", chunk)
    chunk_ = None if v is None else chk.integer(v, f, low=1)
    v = cases if cases is not None else table.get("cases")
    if v is None:
        evs = tuple(
            EventDraw(
                e.fault,
                (float(e.time), float(e.time)),
                float(e.magnitude),
                float(e.ramp),
                None if e.end is None else (e.end - e.time, e.end - e.time),
                e.growth,
            )
            for e in scenario.events
        )
        cases_ = (CaseSpec(scenario.name, evs),) if evs else ()
    else:
        cases_ = _parse_cases(chk, v, scenario, ramps_ != (None,))
    if not cases_ and not ff:
        chk.fail("[sweep].cases", "no fault case and fault_free = false: nothing to run.")
    _check_positive_params(chk, scenario, cases_, mags, pick("magnitudes", magnitudes)[1])
    return SweepSpec(runs_, seed_, methods_, mags, noises, ff, cases_, batch_, chunk_, ramps_)


def _check_positive_params(chk, scenario, cases, mags, field: str) -> None:
    """Refuse magnitudes that would take a physically positive parameter to <= 0."""
    nominal = scenario.nominal_params
    for case in cases:
        for e in case.events:
            for mag in mags:
                bad = nonpositive_param(
                    scenario.plant, nominal, scenario.faults[e.fault], mag * e.magnitude
                )
                if bad:
                    key, value = bad
                    chk.fail(
                        field,
                        f"magnitude {mag!r} x {e.magnitude!r} of fault {e.fault!r} (case "
                        f"{case.name!r}) takes {key} from {nominal[key]!r} to {value!r}, but "
                        f"{key} must stay > 0.",
                    )
