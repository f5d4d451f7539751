"""Runs on measured data: the "truth" record that a run's summary compares against."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from uimm_jax.scenario.measured import MeasuredData, measured_data

__all__ = ["truth_for_measurements"]


def truth_for_measurements(
    setup, measurements, scenario_inputs: Callable[..., np.ndarray]
) -> dict[str, np.ndarray]:
    """The "truth" record of a run on measured data (what the runner's summary needs).

    The true fault set at each sample follows the scenario's ``[[events]]``; the true
    states are unknown (NaN).  Inputs come from the data when it has them, else from the
    scenario's input signal.

    Args:
        setup: the :class:`~uimm_jax.studies.run.RunSetup`.
        measurements: a :class:`MeasuredData` or an ``(N, m)`` array.
        scenario_inputs: ``scenario_inputs(scenario, N) -> (N, p)``, the scenario's input
            sequence (:func:`uimm_jax.studies.truth.scenario_inputs`), used when the data has no
            inputs.

    Returns:
        dict with ``u`` (N, p), ``x`` (N, n) NaN, ``y`` (N, m), ``truth`` (N,) fault-set
        codes and ``t`` (N,), like :func:`uimm_jax.studies.run.simulate_scenario`.
    """
    sc = setup.scenario
    data = (
        measurements
        if isinstance(measurements, MeasuredData)
        else measured_data(sc, measurements, source="measurements")
    )
    N = data.num_steps
    u = data.u if data.u is not None else scenario_inputs(sc, N)
    codes = np.zeros(N, np.int32)
    names = list(setup.table.names)
    for ev, k_ev in zip(sc.events, setup.event_steps, strict=True):
        codes[int(k_ev) :] |= np.int32(1 << names.index(ev.fault))
    t = (np.arange(N) + 1) * float(sc.dt)
    x = np.full((N, sc.plant.state_dim), np.nan)
    return {"u": u, "x": x, "y": data.y, "truth": codes, "t": t}
