"""The engine's dynamics object for a plant: linear (exact KF) or non-linear (EKF)."""

from __future__ import annotations

import numpy as np

from uimm_jax.engine.dynamics import LinearDynamics, NonlinearDynamics
from uimm_jax.plants.base import LinearPlant, NonlinearPlant

__all__ = ["make_dynamics"]


def make_dynamics(plant, dt: float, reference_thetas: np.ndarray):
    """Build the dynamics object that suits ``plant``.

    Args:
        plant: a :class:`~uimm_jax.plants.base.LinearPlant` or
            :class:`~uimm_jax.plants.base.NonlinearPlant`.
        dt: sampling time, s.
        reference_thetas: ``(K, P)`` parameter vectors the bank will use (nominal and fault
            values); see :class:`~uimm_jax.engine.dynamics.LinearDynamics`.

    Returns:
        A :class:`~uimm_jax.engine.dynamics.LinearDynamics` or
        :class:`~uimm_jax.engine.dynamics.NonlinearDynamics`.
    """
    if isinstance(plant, LinearPlant):
        return LinearDynamics(plant, dt, reference_thetas)
    if isinstance(plant, NonlinearPlant):
        return NonlinearDynamics(plant, dt, reference_thetas)
    raise TypeError(f"expected a LinearPlant or NonlinearPlant, got {type(plant).__name__}")
