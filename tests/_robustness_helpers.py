"""Short variants of the shipped tuned scenarios, shared by the robustness test files.

Every engine run in these tests uses the tuned scenarios' diagnoser (same plant, faults,
dt and gate, so ``runner.setup_scenario`` returns the same cached diagnoser) and time
chunks of ``CHUNK`` steps, so the filter and the truth simulation compile once per
session whatever the scenario variant (transition, threshold, noise, events).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from uimm_jax.errors import UIMMWarning
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import dump_scenario, scenario_to_dict

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"
TUNED = {1: SCENARIOS / "paper_sim1_tuned.toml", 2: SCENARIOS / "paper_sim2_tuned.toml"}
CHUNK = 10_000  # steps per compiled chunk: every run below is a multiple of it
# uimm-est's EstSettings as in session 10, before the settings "S10a" became the defaults
# (session 11): the post-declaration rules off; tests of those rules start from it.
SESSION10_EST = {
    "walk_settled": 0.0,
    "settle_steps": 0,
    "post_floor_gap": 0,
    "retract_hold": 0,
    "walk_rel_newest": False,
    "post_floor_mean": 0.0,
    "race_floor_first": True,
    "settle_move": 0.0,
    "low_floor_age": 0,
}


def with_est_settings(setup, settings):
    """``setup`` (a uimm-est ``setup_scenario``) with its diagnoser's ``EstSettings`` replaced."""
    import dataclasses

    diag = dataclasses.replace(setup.diagnoser, settings=settings)
    flt = setup.scenario.filter
    init = diag.init(
        np.asarray(flt.initial_mean),
        np.asarray(flt.initial_cov),
        setup.initial_mode_probs,
        (),
        setup.init_state.imm.mean.dtype,
    )
    return dataclasses.replace(setup, diagnoser=diag, init_state=init)


def tuned_dict(sim: int) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UIMMWarning)
        return scenario_to_dict(load_scenario(TUNED[sim]))


def short_dict(sim: int = 1, duration: float = 1.0, events=(0.3, 0.6), **changes) -> dict:
    """The tuned scenario shortened to ``duration`` s with its events moved to ``events``."""
    d = tuned_dict(sim)
    d["duration"] = duration
    for ev, t in zip(d["events"], events, strict=True):
        ev["time"] = t
    for key, value in changes.items():
        table, _, field = key.rpartition("__")
        target = d
        for part in table.split("__") if table else ():
            target = target[part]
        target[field] = value
    return d


def sim2_ramps(duration: float, ramp: float, second_at: float, magnitude: float = 2.0) -> dict:
    """Sim 2's tuned file: valve wear from 0.5 s and air in oil from ``second_at`` s, both
    at ``magnitude`` over ``ramp`` s, runs of ``duration`` s."""
    d = tuned_dict(2)
    d["duration"] = duration
    d["events"] = [
        {"fault": "valve_wear", "time": 0.5, "magnitude": magnitude, "ramp": ramp},
        {"fault": "air_in_oil", "time": second_at, "magnitude": magnitude, "ramp": ramp},
    ]
    return d


def short_scenario(sim: int = 1, duration: float = 1.0, events=(0.3, 0.6), **changes):
    """:func:`short_dict` validated (``filter__stay=0.999`` changes ``[filter].stay``)."""
    return parse_scenario(short_dict(sim, duration, events, **changes), source=f"short-sim{sim}")


def write_short(path: Path, sim: int = 1, **kw) -> Path:
    """Write a short scenario file (for the CLI)."""
    return dump_scenario(short_dict(sim, **kw), path)


def true_fault_names(scenario) -> list[str]:
    return sorted(e.fault for e in scenario.events)


def assert_declared_right(summary: dict, scenario) -> None:
    """The declared faults are exactly the true ones, each declared after its onset."""
    declared = sorted(d["fault"] for d in summary["declarations"])
    assert declared == true_fault_names(scenario), summary["declarations"]
    assert summary["false_declarations"] == 0, summary["false_declaration_list"]
    assert all(v is not None and v >= 0 for v in summary["detection_delay_s"].values())


def all_finite(outputs: dict) -> bool:
    return all(
        np.all(np.isfinite(np.asarray(outputs[k]))) for k in ("mode_probs", "mean") if k in outputs
    )
