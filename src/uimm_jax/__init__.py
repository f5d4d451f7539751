"""uimm_jax: multi-fault diagnosis with EKF banks, IMM mixing and the updated IMM (UIMM).

After Sun, Wang and Lin, "Multi-Fault Diagnosis Approach Based on Updated Interacting
Multiple Model for Aviation Hydraulic Actuator", Information 2020, 11, 410.

Importing the package changes no JAX configuration (``jax.config``).  float64 is the
reference precision: enable it with ``jax.config.update("jax_enable_x64", True)`` before
building arrays.  For speed on the CPU the import appends two XLA CPU flags to
``XLA_FLAGS`` if no JAX backend has started yet (:mod:`uimm_jax.xla_flags`; opt out with
``UIMM_JAX_NO_XLA_FLAGS=1``).
"""

from importlib.metadata import PackageNotFoundError, version

from uimm_jax.xla_flags import apply_recommended_xla_flags

apply_recommended_xla_flags()  # before anything below imports JAX; no-op once it started

# ruff: noqa: E402

from uimm_jax.engine.bank import FaultTable, fault_table
from uimm_jax.engine.imm import IMMParams, IMMState, StepInfo, imm_step
from uimm_jax.engine.kalman import ekf_predict, ekf_update
from uimm_jax.engine.uimm import DiagInfo, Diagnoser, DiagParams, DiagState
from uimm_jax.engine.uimm_est import build_diagnoser
from uimm_jax.errors import ScenarioError, UIMMWarning
from uimm_jax.plants.base import Fault, LinearPlant, NonlinearPlant
from uimm_jax.plants.registry import get_plant, list_plants, register_plant
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.spec import Scenario
from uimm_jax.scenario.write import dump_scenario
from uimm_jax.studies.imm_filter import IMMResult, LinearGaussianBank, imm_filter
from uimm_jax.studies.run import (
    RunResult,
    filter_measurements,
    run_scenario,
    setup_scenario,
    simulate_scenario,
)

try:
    __version__ = version("uimm-jax")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

__all__ = [
    "DiagInfo",
    "DiagParams",
    "DiagState",
    "Diagnoser",
    "Fault",
    "FaultTable",
    "IMMParams",
    "IMMResult",
    "IMMState",
    "LinearGaussianBank",
    "LinearPlant",
    "NonlinearPlant",
    "RunResult",
    "Scenario",
    "ScenarioError",
    "StepInfo",
    "UIMMWarning",
    "build_diagnoser",
    "dump_scenario",
    "ekf_predict",
    "ekf_update",
    "fault_table",
    "filter_measurements",
    "get_plant",
    "imm_filter",
    "imm_step",
    "list_plants",
    "load_scenario",
    "parse_scenario",
    "register_plant",
    "run_scenario",
    "setup_scenario",
    "simulate_scenario",
]
