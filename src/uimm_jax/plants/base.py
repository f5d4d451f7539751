"""Plant classes: named parameters, fault tables, linear and non-linear models.

A *plant* is what a filter bank is built from: pure functions of the state ``x``,
the input ``u`` and a named parameter vector ``theta``, plus the nominal parameter
values and a default *fault library* (fault name -> the parameters it changes and
their fault values, paper section 3.1).

Two families are supported:

* :class:`LinearPlant` -- ``dx/dt = A(theta) x + B(theta) u`` (or the discrete-time
  ``x[k+1] = A x[k] + B u[k]``) and ``y = C(theta) x + d(theta)``.  Continuous
  models are discretised exactly by zero-order hold (matrix exponential of the
  augmented matrix, :func:`uimm_jax.engine.dynamics.zoh`), so the EKF is the exact KF.
* :class:`NonlinearPlant` -- ``f(x, u, theta)`` (a discrete map, or a continuous
  vector field integrated with ``substeps`` classical RK4 steps per sample) and
  ``h(x, theta)``.  The EKF linearises both with ``jax.jacfwd``.

Plants are made available to scenario files by :mod:`uimm_jax.plants.registry`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, Literal

import numpy as np

from uimm_jax.plants.checks import check_plant_structure

__all__ = ["Fault", "LinearPlant", "NonlinearPlant", "Plant"]


@dataclasses.dataclass(frozen=True)
class Fault:
    """One fault of a fault library.

    Attributes:
        name: identifier used in scenario files and summaries (``valve_wear``).
        values: parameter name -> value of that parameter when the fault is present.
        description: one line on the physics, for documentation and plots.
    """

    name: str
    values: Mapping[str, float]
    description: str = ""


@dataclasses.dataclass(frozen=True, eq=False)
class _PlantBase:
    name: str
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    param_names: tuple[str, ...]
    nominal_values: tuple[float, ...]
    faults: tuple[Fault, ...] = ()
    time: Literal["continuous", "discrete"] = "continuous"
    description: str = ""
    extra_faults: tuple[Fault, ...] = ()
    # Parameters that are physically > 0 (masses, areas, volumes, moduli): scenario files
    # and fault magnitudes that would make one of them <= 0 are refused.
    positive_params: tuple[str, ...] = ()
    # Unit of each state for figures and exports ("m", "m/s", "Pa"); () for none.
    state_units: tuple[str, ...] = ()

    def __post_init__(self):
        check_plant_structure(self)
        if self.state_units and len(self.state_units) != len(self.state_names):
            raise ValueError(
                f"plant {self.name!r}: state_units has {len(self.state_units)} entries for "
                f"{len(self.state_names)} states; give one unit per state (or none)"
            )
        if len(self.param_names) != len(self.nominal_values):
            raise ValueError(
                f"plant {self.name!r}: param_names has {len(self.param_names)} entries but "
                f"nominal_values has {len(self.nominal_values)}; give one nominal value per "
                "parameter."
            )
        if len(set(self.param_names)) != len(self.param_names):
            raise ValueError(f"plant {self.name!r}: parameter names must be unique")
        if self.time not in ("continuous", "discrete"):
            raise ValueError(
                f"plant {self.name!r}: time must be 'continuous' or 'discrete', got {self.time!r}"
            )
        nominal = dict(zip(self.param_names, self.nominal_values, strict=True))
        for p in self.positive_params:
            if p not in nominal:
                raise ValueError(
                    f"plant {self.name!r}: positive_params names unknown parameter {p!r}; "
                    f"known parameters: {', '.join(self.param_names)}"
                )
            if not float(nominal[p]) > 0:
                raise ValueError(
                    f"plant {self.name!r}: {p} is in positive_params but its nominal value "
                    f"is {nominal[p]!r}"
                )
        for fault in self.faults + self.extra_faults:
            for p, v in fault.values.items():
                if p in self.positive_params and not float(v) > 0:
                    raise ValueError(
                        f"plant {self.name!r}: fault {fault.name!r} sets {p} = {v!r}, but {p} "
                        "is in positive_params (must be > 0)"
                    )
            for p in fault.values:
                if p not in self.param_names:
                    raise ValueError(
                        f"plant {self.name!r}: fault {fault.name!r} names unknown parameter "
                        f"{p!r}; known parameters: {', '.join(self.param_names)}"
                    )

    @property
    def state_dim(self) -> int:
        """Number of states ``n``."""
        return len(self.state_names)

    @property
    def input_dim(self) -> int:
        """Number of inputs ``p``."""
        return len(self.input_names)

    @property
    def output_dim(self) -> int:
        """Number of measured outputs ``m``."""
        return len(self.output_names)

    @property
    def nominal(self) -> dict[str, float]:
        """Nominal parameter values by name."""
        return dict(zip(self.param_names, self.nominal_values, strict=True))

    @property
    def fault_library(self) -> dict[str, Fault]:
        """Every fault the plant knows (the default library plus the extra ones)."""
        return {f.name: f for f in self.faults + self.extra_faults}

    def theta(self, overrides: Mapping[str, float] | None = None) -> np.ndarray:
        """Nominal parameter vector with ``overrides`` applied (names checked)."""
        th = np.asarray(self.nominal_values, dtype=np.float64).copy()
        for k, v in (overrides or {}).items():
            if k not in self.param_names:
                raise ValueError(
                    f"unknown parameter {k!r} for plant {self.name!r}; "
                    f"known parameters: {', '.join(self.param_names)}"
                )
            th[self.param_names.index(k)] = float(v)
        return th

    def params(self, theta: Any) -> dict[str, Any]:
        """Map a parameter vector (leading axis = parameters) to a name -> value dict."""
        return {n: theta[i] for i, n in enumerate(self.param_names)}


@dataclasses.dataclass(frozen=True, eq=False)
class LinearPlant(_PlantBase):
    """Linear(-affine) plant ``x' = A x + B u``, ``y = C x + d`` with ``theta``-dependent matrices.

    Attributes:
        matrices: ``matrices(p) -> (A, B, C, d)`` for ONE model, where ``p`` maps parameter
            names to scalars; shapes ``(n, n)``, ``(n, p)``, ``(m, n)``, ``(m,)``.  For
            ``time="continuous"`` A and B are the continuous-time matrices (paper eq. 2),
            discretised by zero-order hold; for ``"discrete"`` they are used as given.
    """

    matrices: Callable[[Mapping[str, Any]], tuple[Any, Any, Any, Any]] | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.matrices is None:
            raise ValueError(f"LinearPlant {self.name!r} needs a matrices(p) function")


@dataclasses.dataclass(frozen=True, eq=False)
class NonlinearPlant(_PlantBase):
    """Non-linear plant ``f(x, u, p)``, ``h(x, p)`` for the extended Kalman filter.

    Attributes:
        f: dynamics for ONE model.  With ``time="discrete"`` it returns ``x[k+1]``; with
            ``"continuous"`` it returns ``dx/dt`` and is integrated by ``substeps`` classical
            Runge-Kutta-4 steps per sample (documented integrator; the EKF Jacobian is that
            of the whole RK4 map, by ``jax.jacfwd``).
        h: measurement function ``h(x, p) -> y``.
        substeps: RK4 steps per sample for continuous-time models.
    """

    f: Callable[[Any, Any, Mapping[str, Any]], Any] | None = None
    h: Callable[[Any, Mapping[str, Any]], Any] | None = None
    substeps: int = 1

    def __post_init__(self):
        super().__post_init__()
        if self.f is None or self.h is None:
            raise ValueError(f"NonlinearPlant {self.name!r} needs both f and h")
        if int(self.substeps) < 1:
            raise ValueError(f"NonlinearPlant {self.name!r}: substeps must be >= 1")


Plant = LinearPlant | NonlinearPlant
