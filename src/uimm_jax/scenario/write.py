"""Write a scenario back: :func:`scenario_to_dict` and TOML text/files.

``load_scenario(dump_scenario(s, path))`` gives ``s`` back field by field (``source``
aside): floats are written in their shortest round-trip form.  The TOML writer at the
end is small and general (tables, arrays of tables, inline values).
"""

from __future__ import annotations

import copy
import datetime
import math
import numbers
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from uimm_jax.errors import UIMMWarning
from uimm_jax.scenario._fields import toml_key, toml_string
from uimm_jax.scenario.parse import parse_with_notes
from uimm_jax.scenario.spec import Scenario

__all__ = ["dump_scenario", "scenario_to_dict", "scenario_to_toml"]


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
    if scenario.plant_module:
        plant["module"] = scenario.plant_module
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
            | ({"ramp": float(e.ramp)} if e.ramp else {})
            | ({} if e.end is None else {"end": float(e.end)})
            | ({} if e.growth == "linear" else {"growth": e.growth})
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
    if flt.est is not None:  # every setting, so that the file does not depend on defaults
        filter_table["est"] = dict(flt.est._asdict())
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
        scenario, notes = parse_with_notes(scenario)
        for note in notes:
            warnings.warn(note, UIMMWarning, stacklevel=2)
    header = (
        f"# Scenario {scenario.name!r}, written by uimm_jax.scenario.write.scenario_to_toml.\n"
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
        scenario, notes = parse_with_notes(scenario)
        for note in notes:
            warnings.warn(note, UIMMWarning, stacklevel=2)
    path.write_text(scenario_to_toml(scenario), encoding="utf-8")
    return path


# -- a small general TOML writer (tables, arrays of tables, inline values) -------------


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
        return toml_string(value)
    if isinstance(value, datetime.date | datetime.time):
        return value.isoformat()
    if isinstance(value, Mapping):
        items = ", ".join(f"{toml_key(k)} = {_toml_value(v)}" for k, v in value.items())
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
    dotted = ".".join(toml_key(p) for p in path)
    if array_item:
        lines += ["", f"[[{dotted}]]"]
    elif path and (plain or not nested):
        lines += ["", f"[{dotted}]"]
    for key, value in plain.items():
        lines.append(f"{toml_key(key)} = {_toml_value(value)}")
    for key, value in nested.items():
        if isinstance(value, Mapping):
            _emit_table(lines, [*path, key], value, array_item=False)
        else:
            for item in value:
                _emit_table(lines, [*path, key], item, array_item=True)
