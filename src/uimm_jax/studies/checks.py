"""Checks of the run-level arguments: the scenario, the method, the setup and run data.

Each raises ``ValueError`` (``TypeError`` for a wrong kind of object) naming the argument;
the plant of a scenario is checked once per plant object.
"""

from __future__ import annotations

import weakref

import numpy as np

from uimm_jax._checks import (
    check_float_dtype,
    check_inputs,
    check_measurements,
    check_positive_finite,
    check_positive_int,
)
from uimm_jax.plants.checks import check_plant_functions, check_plant_structure
from uimm_jax.scenario.spec import Scenario

__all__ = ["check_method", "check_run_data", "check_scenario", "check_setup_args"]


def check_scenario(scenario, name: str = "scenario") -> None:
    """Require a :class:`~uimm_jax.scenario.spec.Scenario` (not a path or a dict)."""
    if not isinstance(scenario, Scenario):
        hint = (
            "load a file with uimm_jax.load_scenario(path)"
            if isinstance(scenario, str | bytes) or hasattr(scenario, "__fspath__")
            else "validate a dict with uimm_jax.parse_scenario(d)"
            if isinstance(scenario, dict)
            else "build one with uimm_jax.load_scenario or uimm_jax.parse_scenario"
        )
        raise TypeError(f"{name}: expected a Scenario, got {type(scenario).__name__}; {hint}")


def check_method(method, name: str = "method") -> None:
    """``"uimm"``, ``"imm"`` or ``"uimm-est"``."""
    if method not in ("uimm", "imm", "uimm-est"):
        raise ValueError(f"{name}: expected 'uimm', 'imm' or 'uimm-est', got {method!r}")


_CHECKED_PLANTS: weakref.WeakSet = weakref.WeakSet()


def check_setup_args(scenario, method, dtype, magnitude_scale) -> None:
    """Arguments of :func:`uimm_jax.studies.run.setup_scenario` (and its plant, once per plant)."""
    check_scenario(scenario)
    if method is not None:
        check_method(method)
    if dtype is not None:
        check_float_dtype(dtype)
    check_positive_finite(magnitude_scale, "magnitude_scale")
    plant = scenario.plant
    if plant not in _CHECKED_PLANTS:
        check_plant_structure(plant)
        check_plant_functions(plant)
        _CHECKED_PLANTS.add(plant)


def check_run_data(setup, y, u, chunk) -> tuple[np.ndarray, np.ndarray | None]:
    """Arguments of :func:`uimm_jax.studies.run.filter_measurements`: ``(N, m)`` / ``(N, p)``."""
    plant = setup.scenario.plant
    check_positive_int(chunk, "chunk")
    y = check_measurements(y, plant.output_dim)
    if u is not None:
        u = check_inputs(u, y.shape[0], plant.input_dim)
    return y, u
