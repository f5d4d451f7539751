"""Read and validate the TOML description of one experiment into a :class:`Scenario`.

Loading is strict: every problem raises :class:`~uimm_jax.errors.ScenarioError`, whose
message names the file, the field (``[filter].transition``) and what is expected.
Values that are accepted but changed (initial mode probabilities that do not sum to 1)
raise a :class:`~uimm_jax.errors.UIMMWarning` saying what was changed.  The schema is
documented key by key in ``docs/scenarios.md``; the ``[sweep]`` table is kept raw here and
validated by :func:`uimm_jax.scenario.sweep.sweep_spec`.

Example::

    scenario = load_scenario("scenarios/paper_sim1.toml")
    scenario.num_steps            # 1_000_000
    scenario.transition_matrix()  # (4, 4), paper eq. (37)
    dump_scenario(scenario, "copy.toml")   # load_scenario("copy.toml") gives it back

This module is pure Python/NumPy (stdlib ``tomllib``); it imports no JAX.
"""

from __future__ import annotations

import copy
import difflib
import os
import tomllib
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from uimm_jax._checks import MAX_INT32, MAX_SEED, type_name
from uimm_jax.errors import ScenarioError, UIMMWarning
from uimm_jax.plants.base import Plant
from uimm_jax.plants.registry import get_plant, list_plants
from uimm_jax.scenario._fields import frozen, plain, suggest, toml_key
from uimm_jax.scenario._filter import FilterParser
from uimm_jax.scenario._plant import import_module_of
from uimm_jax.scenario.spec import (
    INPUT_KINDS,
    METHODS,
    EventSpec,
    InputSpec,
    Scenario,
    nonpositive_param,
)

__all__ = ["load_scenario", "parse_scenario", "parse_with_notes"]


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
    scenario, notes = parse_with_notes(data, source)
    for note in notes:
        warnings.warn(note, UIMMWarning, stacklevel=2)
    return scenario


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
    scenario, notes = parse_with_notes(data, source)
    for note in notes:
        warnings.warn(note, UIMMWarning, stacklevel=2)
    return scenario


def parse_with_notes(data: Mapping[str, Any], source: str = "<dict>") -> tuple[Scenario, list[str]]:
    """Validate a scenario dict; return it with the warnings to emit (not emitted here).

    Raises:
        ScenarioError: the dict breaks the schema.
    """
    return _Parser(source).parse(data)


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
_PLANT_KEYS = ("model", "params", "module")
_INPUT_KEYS = ("kind", "amplitude", "frequency", "offset", "step_time")
_NOISE_KEYS = ("process", "measurement")
_EVENT_KEYS = ("time", "fault", "magnitude", "ramp", "end", "growth")

_HINTS = {
    "name": 'a label for outputs, e.g. name = "paper-sim1"',
    "duration": "the simulated time in seconds, e.g. duration = 100.0",
    "dt": "the sample time in seconds, e.g. dt = 1.0e-4",
    "plant": '[plant] with model = "hydraulic_actuator" (a registered plant name)',
    "model": 'a registered plant name, e.g. model = "hydraulic_actuator"',
    "module": 'a Python file next to the scenario or an importable module, e.g. "my_plants"',
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


class _Parser(FilterParser):
    """Validates one scenario dict; collects warnings to be emitted by the caller.

    ``[filter]`` is read by :meth:`FilterParser.parse_filter` (:mod:`uimm_jax.scenario._filter`).
    """

    HINTS = _HINTS

    # -- the schema ---------------------------------------------------------------------

    def parse(self, data: Mapping[str, Any]) -> tuple[Scenario, list[str]]:
        top = self.table(plain(data, "", self.source), "top level")
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

        plant_module = import_module_of(self, top["plant"])
        plant, plant_params = self.parse_plant(top["plant"])
        nominal = {k: float(v) for k, v in plant.nominal.items()}
        nominal.update(plant_params)
        input_spec = self.parse_input(top["input"])
        self.check_input_timing(input_spec, duration, dt)
        process, measurement = self.parse_noise(top["noise"], plant)
        faults = self.parse_faults(top.get("faults"), plant, nominal)
        events = self.parse_events(top.get("events"), faults, duration, dt, plant, nominal)
        raw_sweep = top.get("sweep")
        methods = raw_sweep.get("methods") if isinstance(raw_sweep, Mapping) else None
        filter_spec = self.parse_filter(top["filter"], plant, len(faults), methods)
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
            process_noise=frozen(process),
            measurement_noise=frozen(measurement),
            faults=faults,
            events=events,
            filter=filter_spec,
            sweep=sweep,
            source=self.source,
            plant_module=plant_module,
        )
        return scenario, self.notes

    def parse_plant(self, value: Any) -> tuple[Plant, dict[str, float]]:
        table = self.table(value, "[plant]")
        self.keys(table, "[plant]", _PLANT_KEYS, ("model",))
        model = self.string(table["model"], "[plant].model")
        try:
            plant = get_plant(model)
        except ValueError as exc:
            known = list_plants()
            if model in known:  # an installed entry point that fails to load
                self.fail("[plant].model", f"{exc}.")
            self.fail(
                "[plant].model",
                f"unknown plant model {model!r}.{suggest(model, known)} Registered models: "
                f"{', '.join(known)} (register your own with uimm_jax.register_plant(), "
                '[plant] module = "my_plants" or the entry-point group "uimm_jax.plants").',
            )
        params: dict[str, float] = {}
        if "params" in table:
            ptable = self.table(table["params"], "[plant.params]")
            for key, v in ptable.items():
                field = self.path("[plant.params]", key)
                self.param_name(key, field, plant)
                params[key] = self.plant_positive(plant, key, self.number(v, field), field)
        return plant, params

    def parse_input(self, value: Any) -> InputSpec:
        table = self.table(value, "[input]")
        self.keys(table, "[input]", _INPUT_KEYS, ("kind", "amplitude"))
        kind = self.string(table["kind"], "[input].kind")
        if kind not in INPUT_KINDS:
            self.fail(
                "[input].kind",
                f"unknown input kind {kind!r}.{suggest(kind, INPUT_KINDS)} Expected one of: "
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
            header = f"[faults.{toml_key(fname)}]"
            ftable = self.table(ftable, header, " of parameter = fault value")
            if not ftable:
                if fname not in library:
                    self.fail(
                        header,
                        f"empty fault table, and {fname!r} is not in the fault library of "
                        f"plant {plant.name!r}.{suggest(fname, library)} Either give its "
                        "parameters (parameter = fault value) or use a library fault: "
                        f"{', '.join(library)}.",
                    )
                values = {k: float(v) for k, v in library[fname].values.items()}
            else:
                values = {}
                for key, v in ftable.items():
                    field = self.path(header, key)
                    self.param_name(key, field, plant)
                    values[key] = self.plant_positive(plant, key, self.number(v, field), field)
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
                f"{type_name(value)}.",
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
            step = self.onset_step(time, f"{header}.time", dt, num_steps)
            fault = self.string(entry["fault"], f"{header}.fault")
            if fault not in faults:
                extra = ""
                if fault in plant.fault_library:
                    extra = (
                        f" {fault!r} is in the plant's fault library: add an empty "
                        f"[faults.{toml_key(fault)}] table to diagnose it."
                    )
                self.fail(
                    f"{header}.fault",
                    f"unknown fault {fault!r}: not in this scenario's fault library "
                    f"({', '.join(faults)}).{suggest(fault, faults)}{extra}",
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
            ramp = self.number(entry.get("ramp", 0.0), f"{header}.ramp", low=0.0, unit="(s)")
            end = None
            if "end" in entry:
                end = self.end_time(entry["end"], f"{header}.end", time, step, dt, duration)
            growth = self.growth(entry, header, ramp)
            events.append(EventSpec(time, fault, magnitude, ramp, end, growth))
        return tuple(sorted(events, key=lambda e: e.time))
