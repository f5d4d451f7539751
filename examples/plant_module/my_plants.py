"""A plant of your own, for scenario files: ``[plant] module = "my_plants"``.

``uimm-jax run examples/plant_module/mass_spring.toml`` imports this file (it sits next to
the scenario) before it looks the plant up, and registers every plant defined at its top
level.  Nothing else is needed: no ``register_plant`` call, no installed package.

The plant: a mass on a spring and a damper, pushed by a force ``F``,

    m x'' = F - k x - c v,

with position and velocity measured.  Two faults: the spring cracks (its stiffness drops
from 100 to 60 N/m) and the damper leaks (its damping drops from 2 to 0.5 N s/m).
"""

import jax.numpy as jnp

from uimm_jax import Fault, LinearPlant


def matrices(p):
    """Continuous-time ``(A, B, C, d)`` of one model; ``p`` maps parameter names to values."""
    A = jnp.array([[0.0, 1.0], [-p["k"] / p["m"], -p["c"] / p["m"]]])
    B = jnp.array([[0.0], [1.0 / p["m"]]])
    return A, B, jnp.eye(2), jnp.zeros(2)


MASS_SPRING = LinearPlant(
    name="mass_spring",
    state_names=("x", "v"),
    state_units=("m", "m/s"),
    input_names=("F",),
    output_names=("x", "v"),
    param_names=("m", "k", "c"),
    nominal_values=(1.0, 100.0, 2.0),
    faults=(Fault("spring_crack", {"k": 60.0}), Fault("damper_leak", {"c": 0.5})),
    matrices=matrices,
)
