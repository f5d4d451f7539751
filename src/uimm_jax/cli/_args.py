"""Checks of command-line flags shared by the sub-commands (each error names its flag)."""

from __future__ import annotations

import copy
import math
import os
from pathlib import Path

__all__ = ["MAX_HOST_DEVICES", "check_out_file", "check_weights", "with_duration"]

MAX_HOST_DEVICES = max(64, 4 * (os.cpu_count() or 1))
"""Upper bound of ``--host-devices``: every XLA CPU device costs memory and threads, and
tens of thousands of them exhaust the machine before JAX reports anything."""


def _scaled(time, factor: float):
    return [float(t) * factor for t in time] if isinstance(time, list) else float(time) * factor


def with_duration(scenario, duration, flag: str):
    """The scenario lasting ``duration`` s, its event times scaled by the same factor.

    An event's ``time`` and ``end`` are scaled, and the onsets of the ``[sweep]`` cases
    (times and windows) too, so that every event keeps its place in the run; lengths
    (``ramp``, a case's ``duration``) are kept.  Refuses a duration that is not a finite number > 0
    or not a whole number of samples, naming ``flag``.
    """
    from uimm_jax._checks import check_positive_finite
    from uimm_jax.errors import ScenarioError
    from uimm_jax.scenario.parse import parse_scenario
    from uimm_jax.scenario.write import scenario_to_dict

    duration = check_positive_finite(duration, flag)
    if duration == float(scenario.duration):
        return scenario
    factor = duration / float(scenario.duration)
    d = scenario_to_dict(scenario)
    d["duration"] = duration
    for ev in d.get("events", []):
        for key in ("time", "end"):
            if key in ev:
                ev[key] = _scaled(ev[key], factor)
    sweep = copy.deepcopy(d.get("sweep")) or {}
    for case in sweep.get("cases", []) if isinstance(sweep.get("cases"), list) else []:
        for ev in case.get("events", []) if isinstance(case, dict) else []:
            if isinstance(ev, dict) and "time" in ev:
                ev["time"] = _scaled(ev["time"], factor)
    if sweep:
        d["sweep"] = sweep
    try:
        return parse_scenario(d, source=f"{scenario.source} ({flag} {duration:g})")
    except ScenarioError as err:
        raise ValueError(f"{flag} {duration:g}: {err.detail}") from None


def check_weights(text: str, names: tuple[str, ...], flag: str = "--weights") -> tuple:
    """Exactly ``len(names)`` comma-separated finite numbers >= 0."""
    parts = [p.strip() for p in text.split(",")]
    want = ",".join(names)
    if len(parts) != len(names):
        raise ValueError(
            f"{flag}: expected {len(names)} comma-separated numbers {want}, got "
            f"{len(parts)} in {text!r}"
        )
    values = []
    for name, part in zip(names, parts, strict=True):
        try:
            v = float(part)
        except ValueError:
            raise ValueError(f"{flag}: {name} = {part!r} is not a number ({want})") from None
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{flag}: {name} = {v!r}; expected a finite number >= 0")
        values.append(v)
    return tuple(values)


def check_out_file(path: str, flag: str = "--out", suffix: str = ".toml") -> Path:
    """An output file: not empty, not a folder, with ``suffix``; its folder is created."""
    from uimm_jax._checks import check_out_dir

    if not str(path).strip():
        raise ValueError(f"{flag}: empty path; give a file name, e.g. tuned{suffix}")
    out = Path(path)
    if out.is_dir():
        raise ValueError(f"{flag}: {str(out)!r} is a folder; give a file name, e.g. tuned{suffix}")
    if out.suffix != suffix:
        raise ValueError(
            f"{flag}: {str(out)!r}: the file is written as TOML; name it with {suffix!r}, "
            f"e.g. {str(out.with_suffix(suffix))!r}"
        )
    check_out_dir(out.parent if str(out.parent) else ".", f"{flag} (its folder)")
    return out
