"""The plant registry: scenario files name a plant (``[plant] model = "..."``) by its name.

The built-in plants (:mod:`uimm_jax.plants.hydraulic_actuator`) are registered when this
module is imported.  Users add their own plant without editing the package::

    plant = uimm_jax.LinearPlant(name="my_motor", ..., matrices=my_fn)
    uimm_jax.register_plant(plant)

after which scenario files can say ``[plant] model = "my_motor"``.
"""

from __future__ import annotations

from uimm_jax.plants.base import LinearPlant, NonlinearPlant, Plant
from uimm_jax.plants.hydraulic_actuator import HYDRAULIC_ACTUATOR

__all__ = ["get_plant", "list_plants", "register_plant"]

_BUILTIN_PLANTS = (HYDRAULIC_ACTUATOR,)

_REGISTRY: dict[str, Plant] = {}


def register_plant(plant: Plant, *, overwrite: bool = False) -> Plant:
    """Make ``plant`` available to scenario files under ``plant.name``.

    Args:
        plant: a :class:`LinearPlant` or :class:`NonlinearPlant`.
        overwrite: replace an existing plant of the same name instead of raising.

    Returns:
        The plant, so the call can be used as an expression.
    """
    if not isinstance(plant, LinearPlant | NonlinearPlant):
        raise TypeError("register_plant expects a LinearPlant or NonlinearPlant")
    if plant.name in _REGISTRY and not overwrite:
        raise ValueError(
            f"a plant named {plant.name!r} is already registered; pass overwrite=True to replace it"
        )
    _REGISTRY[plant.name] = plant
    return plant


def get_plant(name: str) -> Plant:
    """Look a registered plant up by name, with a helpful error if it is unknown."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(
            f"unknown plant model {name!r}; registered models: {', '.join(sorted(_REGISTRY))}. "
            "Register your own with uimm_jax.register_plant()."
        ) from None


def list_plants() -> list[str]:
    """Names of all registered plants."""
    return sorted(_REGISTRY)


for _plant in _BUILTIN_PLANTS:
    register_plant(_plant)
