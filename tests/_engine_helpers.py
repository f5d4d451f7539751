"""Small helpers shared by the engine tests: running ``imm_filter`` on a reference problem
(:func:`_reference.make_linear_problem`) and counting XLA compilations."""

from __future__ import annotations

import contextlib

import jax

from uimm_jax.studies.imm_filter import LinearGaussianBank, imm_filter

BACKEND_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


def run_imm_filter(problem: dict, measurements=None, **kwargs):
    """``imm_filter`` on a problem dict (``measurements`` defaults to the problem's)."""
    bank = LinearGaussianBank(*(problem[k] for k in ("A", "B", "C", "Q", "R")))
    return imm_filter(
        bank,
        problem["transition"],
        problem["mu0"],
        problem["x0"],
        problem["P0"],
        problem["inputs"],
        problem["measurements"] if measurements is None else measurements,
        **kwargs,
    )


@contextlib.contextmanager
def count_backend_compiles():
    """Collect the names of the XLA compilations that happen inside the block."""
    names = []

    def listener(event, duration, **kwargs):
        if event == BACKEND_COMPILE_EVENT:
            names.append(kwargs.get("fun_name", "?"))

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def biased_sensors_dict(dt: float = 1e-3) -> dict:
    """The user-plant scenario of the faults issue, as a dict (its plant registered).

    A 3-state discrete linear plant whose three sensors get additive biases (10 sd at
    magnitude 1): a step (bias0, 1.5 at 0.3 s), a 50 ms ramp (bias1, 0.7 at 0.8 s) and a
    bias that ends (bias2, 1.2 from 1.2 s to 1.6 s); ``method = "uimm-est"``.  Used by
    ``tests/engine/test_fault_sizes.py`` and ``benchmarks/results/session12_sec``'s probe.
    """
    import jax.numpy as jnp

    import uimm_jax
    from uimm_jax import Fault, LinearPlant

    def matrices(p):
        A = jnp.array([[0.99, 0.05, 0.0], [-0.05, 0.98, 0.0], [0.0, 0.0, 0.97]])
        B = jnp.array([[0.0], [0.1], [0.05]])
        return A, B, jnp.eye(3), jnp.stack([p["b0"], p["b1"], p["b2"]])

    plant = LinearPlant(
        name="biased_sensors",
        state_names=("a", "b", "c"),
        input_names=("u",),
        output_names=("a", "b", "c"),
        param_names=("b0", "b1", "b2"),
        nominal_values=(0.0, 0.0, 0.0),
        faults=(
            Fault("bias0", {"b0": 0.1}),
            Fault("bias1", {"b1": 0.1}),
            Fault("bias2", {"b2": 0.1}),
        ),
        time="discrete",
        matrices=matrices,
    )
    uimm_jax.register_plant(plant, overwrite=True)
    return {
        "name": "biases",
        "duration": 2.0,
        "dt": dt,
        "seed": 0,
        "plant": {"model": "biased_sensors"},
        "input": {"kind": "sine", "amplitude": 1.0, "frequency": 2.0},
        "noise": {"process": [1e-6] * 3, "measurement": [1e-4] * 3},  # sd 0.01: a bias of 1 = 10 sd
        "faults": {"bias0": {}, "bias1": {}, "bias2": {}},
        "events": [
            {"time": 0.3, "fault": "bias0", "magnitude": 1.5},  # a step
            {"time": 0.8, "fault": "bias1", "magnitude": 0.7, "ramp": 0.05},  # a ramp
            {"time": 1.2, "fault": "bias2", "magnitude": 1.2, "end": 1.6},  # a bias that ends
        ],
        "filter": {
            "method": "uimm-est",
            "stay": 0.999,
            "initial_mean": [0.0, 0.0, 0.0],
            "initial_cov": 1e-2,
            "decision": {"threshold": 0.99, "hold": 10},
        },
    }
