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
