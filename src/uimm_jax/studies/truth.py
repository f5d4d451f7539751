"""The truth plan of a scenario's runs: one builder for ``run``, ``sweep`` and ``tune``.

:func:`build_truth_plan` turns per-run fault onsets and magnitudes into the engine's
:class:`~uimm_jax.engine.truth.TruthPlan` (:func:`uimm_jax.engine.truth.truth_plan`:
phases -> parameters -> discretised dynamics -> finite check) with the scenario's noise,
and names the scenario and the offending fault phase when a phase's dynamics overflow.
:func:`scenario_onsets` reads a scenario's own ``[[events]]`` and :func:`scenario_inputs`
evaluates its input signal.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine.truth import (
    GROWTH_KINDS,
    InputSignal,
    NonFiniteTruth,
    TruthPlan,
    fault_levels,
    input_value,
    truth_plan,
)

__all__ = [
    "build_truth_plan",
    "scenario_inputs",
    "scenario_onsets",
    "scenario_ramps",
    "true_magnitudes",
]


def scenario_ramps(scenario, names):
    """Ramp length, end step and growth of each fault from a scenario's ``[[events]]``.

    Returns:
        ``(ramp (F,) int64, end (F,) int64, growth (F,) int64)``: ramp steps
        ``round(ramp / dt)`` (0: abrupt), end step ``round(end / dt)`` (``-1``: never),
        growth code (:data:`~uimm_jax.engine.truth.GROWTH_KINDS`).
    """
    names = list(names)
    ramp = np.zeros(len(names), np.int64)
    end = np.full(len(names), -1, np.int64)
    growth = np.zeros(len(names), np.int64)
    for ev in scenario.events:
        j = names.index(ev.fault)
        ramp[j] = int(round(ev.ramp / scenario.dt))
        growth[j] = GROWTH_KINDS.index(ev.growth)
        if ev.end is not None:
            end[j] = int(round(ev.end / scenario.dt))
    return ramp, end, growth


def true_magnitudes(scenario, names, num_steps: int, magnitude_scale: float = 1.0) -> np.ndarray:
    """``(N, F)`` the truth's magnitude of each fault at each step (0: absent).

    The truth plan's own rule (:func:`~uimm_jax.engine.truth.fault_levels`: along a
    ramp, 0 after an end), at every step.
    """
    onset, magnitude, _ = scenario_onsets(scenario, names, magnitude_scale)
    ramp, end, growth = scenario_ramps(scenario, names)
    return fault_levels(onset, magnitude, ramp, end, np.arange(num_steps), growth=growth)[0]


def scenario_onsets(scenario, names, magnitude_scale: float = 1.0):
    """Onset step and magnitude of each fault from a scenario's ``[[events]]``.

    Args:
        scenario: the :class:`~uimm_jax.scenario.spec.Scenario`.
        names: the bank's fault names (the order of the arrays).
        magnitude_scale: multiplies every event's magnitude.

    Returns:
        ``(onset (F,) int64, magnitude (F,), event_steps (E,) int64)``: onset ``-1`` for
        a fault without an event; an event at time ``T`` acts from step ``round(T / dt)``;
        ``event_steps`` is the step of each event in the scenario's order.
    """
    names = list(names)
    onset = np.full(len(names), -1, np.int64)
    magnitude = np.ones(len(names))
    steps = []
    for ev in scenario.events:
        j = names.index(ev.fault)
        steps.append(int(round(ev.time / scenario.dt)))
        onset[j] = steps[-1]
        magnitude[j] = ev.magnitude * magnitude_scale
    return onset, magnitude, np.array(steps, np.int64)


def build_truth_plan(
    scenario,
    dyn,
    table,
    onset,
    magnitude,
    *,
    dtype,
    num_phases: int | None = None,
    noise_scale=None,
    ramp=None,
    end=None,
    growth=None,
    where: str = "",
    hint: str = "[[events]].magnitude, the fault values and [plant.params]",
) -> TruthPlan:
    """The truth plan of one run (``onset`` ``(F,)``) or a batch (``(B, F)``) of a scenario.

    Args:
        scenario: the :class:`~uimm_jax.scenario.spec.Scenario` (plant, truth noise, source).
        dyn: the plant's dynamics object (the diagnoser's).
        table: the bank's :class:`~uimm_jax.engine.bank.FaultTable`.
        onset: ``(*runs, F)`` onset step of each fault (``-1``: absent).
        magnitude: ``(*runs, F)`` magnitude of each fault.
        dtype: float dtype.
        num_phases: phases per run (default: the fewest that hold every run's events).
        noise_scale: optional ``(B,)`` scales of the truth noise standard deviations.
        ramp: optional ``(*runs, F)`` ramp steps of each fault (0: abrupt).
        end: optional ``(*runs, F)`` end step of each fault (``-1``: never).
        growth: optional ``(*runs, F)`` growth code of each fault's ramp.
        where: prefix of the error message naming the input (e.g. ``"[sweep]: "``).
        hint: what the error message asks to check.

    Returns:
        The :class:`~uimm_jax.engine.truth.TruthPlan`.

    Raises:
        ValueError: a phase's discretised dynamics are not finite.
    """
    try:
        return truth_plan(
            dyn,
            table,
            onset,
            magnitude,
            scenario.process_noise,
            scenario.measurement_noise,
            num_phases=num_phases,
            noise_scale=noise_scale,
            dtype=dtype,
            ramp=ramp,
            end=end,
            growth=growth,
        )
    except NonFiniteTruth as err:
        faults = [
            f"{name} (magnitude {float(err.magnitude[j])!r})"
            for j, name in enumerate(table.names)
            if err.present[j]
        ]
        changed = {
            k: float(v)
            for k, v, v0 in zip(scenario.plant.param_names, err.theta, table.nominal, strict=True)
            if v != v0
        }
        phase = f"after {', '.join(faults)}" if faults else "at the nominal parameters"
        raise ValueError(
            f"{scenario.source}: {where}the truth's discretised dynamics are not finite "
            f"{phase} (parameters {changed}): check {hint}."
        ) from None


def scenario_inputs(scenario, num_steps: int | None = None, dtype=None) -> np.ndarray:
    """The input sequence ``u_k = u(k dt)`` of a scenario, ``(N, p)`` on the host."""
    num_steps = scenario.num_steps if num_steps is None else num_steps
    t = np.arange(num_steps) * float(scenario.dt)
    sig = InputSignal.from_spec(scenario.input, jnp.float64)
    with jax.default_device(jax.local_devices(backend="cpu")[0]):
        u = np.asarray(input_value(sig, jnp.asarray(t)))
    return np.repeat(u[:, None], scenario.plant.input_dim, axis=1).astype(dtype or np.float64)
