"""A ramp's shape: linear, or the exponential incipient-fault profile, in every path."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from _robustness_helpers import short_dict
from uimm_jax.engine.truth import (
    EXP_TAIL,
    NEVER,
    RAMP_SEGMENTS,
    fault_breakpoints,
    fault_levels,
    truth_plan,
)
from uimm_jax.errors import ScenarioError
from uimm_jax.scenario.parse import parse_scenario
from uimm_jax.scenario.sweep import sweep_spec
from uimm_jax.scenario.write import scenario_to_toml


def _exp_profile(k, onset, mag, tau):
    """The documented curve, written out: ``mag (1 - exp(-(k - onset) / tau)) / (1 - 1e-6)``
    from the onset, held at ``mag`` once it gets there, 0 before."""
    out = np.zeros(len(k))
    for i, kk in enumerate(k):
        if kk >= onset:
            out[i] = min(1.0, (1.0 - math.exp(-(kk - onset) / tau)) / (1.0 - 1e-6)) * mag
    return out


def test_levels_follow_the_exponential_curve_and_the_linear_default_is_unchanged():
    k = np.arange(0, 60000, 7)
    lv, present = fault_levels([100, 50], [2.0, 0.5], [3000, 400], None, k, growth=[1, 0])
    np.testing.assert_allclose(lv[:, 0], _exp_profile(k, 100, 2.0, 3000), rtol=0, atol=1e-14)
    np.testing.assert_allclose(lv[:, 1], 0.5 * np.clip((k - 50) / 400, 0, 1) * (k >= 50), atol=0)
    assert present[:, 0].tolist() == (k >= 100).tolist()
    # 63 % after one time constant; the magnitude itself after 13.8 of them
    assert fault_levels([0], [1.0], [1000], None, [1000], growth=[1])[0][0, 0] == pytest.approx(
        1 - math.exp(-1), rel=2e-6
    )
    assert fault_levels([0], [1.0], [1000], None, [13816], growth=[1])[0][0, 0] == 1.0
    # no growth code: the linear ramp, bit for bit
    a = fault_levels([100], [2.0], [3000], [40000], k)
    b = fault_levels([100], [2.0], [3000], [40000], k, growth=[0])
    np.testing.assert_array_equal(a[0], b[0])


@pytest.mark.parametrize("tau", [3, 200, 3000, 60000])
def test_exponential_knots_interpolate_the_curve_within_its_bound(tau):
    """Linear interpolation between the breakpoints (what the truth does) is within
    ``M / (2 S^2)`` of the curve at every step, twice that where the knots round to
    steps a segment or two apart (measured: 1.5x at 200 steps), for any time constant."""
    onset, mag = 100, 3.0
    steps, lv, ends, present = fault_breakpoints([onset], [mag], ramp=[tau], growth=[1])
    length = math.ceil(tau * math.log(1 / EXP_TAIL))
    assert steps[0] == onset and steps[-1] == onset + length and len(steps) <= RAMP_SEGMENTS + 1
    assert np.all(np.diff(steps) > 0) and present.all()
    assert lv[0, 0] == 0.0 and lv[-1, 0] == mag
    np.testing.assert_array_equal(ends[:-1, 0], lv[1:, 0])  # no jump at a knot
    k = np.arange(onset, onset + length + 5)
    interp = np.interp(k, steps, lv[:, 0])
    err = np.max(np.abs(interp - _exp_profile(k, onset, mag, tau)))
    bound = mag / (2 * RAMP_SEGMENTS**2)
    assert err <= (2.0 if tau < 1000 else 1.2) * bound, err / bound  # 3000: 0.71


def test_an_end_cuts_an_exponential_growth():
    steps, lv, ends, present = fault_breakpoints([100], [1.0], [5000], [2000], growth=[1])
    assert steps[-1] == 2000 and lv[-1, 0] == 0.0 and not present[-1, 0]
    assert ends[-2, 0] == pytest.approx(_exp_profile([2000], 100, 1.0, 5000)[0], rel=1e-12)


def test_exponential_truth_states_follow_the_curve():
    """Air in oil x3 growing with a 0.05 s time constant: the truth's states with the 256
    knots stay within 0.05 measurement sd of a truth with a segment at every step."""
    import jax

    from uimm_jax.engine.scan import truth_scan
    from uimm_jax.engine.truth import InputSignal
    from uimm_jax.studies.run import setup_scenario

    jax.config.update("jax_enable_x64", True)
    setup = setup_scenario(parse_scenario(short_dict(sim=2, duration=0.3, events=(0.05, 0.1))))
    sc, dyn = setup.scenario, setup.diagnoser.dyn
    R = np.asarray(sc.measurement_noise)
    states = {}
    for segments in (RAMP_SEGMENTS, 7000):
        plan = truth_plan(
            dyn, setup.table, np.array([-1, -1, 200]), np.array([1.0, 1.0, 3.0]),
            np.zeros((3, 3)), R, ramp=np.array([0, 0, 500]), segments=segments,
            growth=np.array([0, 0, 1]),
        )  # fmt: skip
        ks = jax.numpy.arange(3000, dtype=jax.numpy.int32)
        signal = InputSignal.from_spec(sc.input)
        zero = np.zeros(2, np.uint32)
        _, (_u, x, _y, _c) = truth_scan(dyn, sc.dt, 1, plan, signal, zero, jax.numpy.zeros(3), ks)
        states[segments] = np.asarray(x)
    off = np.max(np.abs(states[RAMP_SEGMENTS] - states[7000]), axis=0) / np.sqrt(np.diag(R))
    moved = np.max(np.abs(states[7000][-1] - states[7000][199]))
    assert off.max() < 0.05 and moved > 0, off


def test_events_and_sweep_cases_take_growth_and_write_it_back():
    d = short_dict(duration=1.0, events=(0.2, 0.4))
    d["events"][0].update(ramp=0.05, growth="exponential")
    sc = parse_scenario(d)
    assert sc.events[0].growth == "exponential" and sc.events[1].growth == "linear"
    again = parse_scenario(tomllib.loads(scenario_to_toml(sc)))
    assert again.events == sc.events
    assert "growth" not in scenario_to_toml(parse_scenario(short_dict(duration=1.0)))
    for value, msg in (
        ("exponentail", r"\[\[events\]\]\[0\]\.growth: unknown growth 'exponentail'\. Did you"),
        (3, r"\]\[0\]\.growth: must be a string, one of linear, exponential; got an integer"),
    ):
        bad = short_dict(duration=1.0, events=(0.2, 0.4))
        bad["events"][0].update(ramp=0.05, growth=value)
        with pytest.raises(ScenarioError, match=msg):
            parse_scenario(bad)
    bad = short_dict(duration=1.0, events=(0.2, 0.4))
    bad["events"][0]["growth"] = "exponential"
    with pytest.raises(ScenarioError, match=r"\.growth: 'exponential' needs .*\.ramp > 0"):
        parse_scenario(bad)
    # [sweep] cases and the scenario's own events
    case = {"name": "g", "events": [{"fault": "leakage", "time": 0.2, "ramp": 0.1}]}
    case["events"][0]["growth"] = "exponential"
    spec = sweep_spec(sc, runs=2, cases=[case])
    assert spec.cases[0].events[0].growth == "exponential"
    assert sweep_spec(sc, runs=2).cases[0].events[0].growth == "exponential"
    del case["events"][0]["ramp"]  # the time constant from the ramps axis, else refused
    assert sweep_spec(sc, runs=2, cases=[case], ramps=[0.1]).ramps == (0.1,)
    with pytest.raises(ScenarioError, match=r"events\[0\]\.growth: 'exponential' needs"):
        sweep_spec(sc, runs=2, cases=[case])
    case["events"][0]["growth"] = "linar"
    with pytest.raises(ScenarioError, match=r"cases\[0\]\.events\[0\]\.growth: .*'linear'"):
        sweep_spec(sc, runs=2, cases=[case])


def test_runs_and_sweeps_hand_the_growth_to_the_truth(monkeypatch):
    """A single run's plan, ``true_magnitudes`` and a sweep's batch all use the events'
    growth (the sweep is stopped at its first batch's truth plan)."""
    from uimm_jax.studies import sweep as sweep_mod
    from uimm_jax.studies.run import setup_scenario
    from uimm_jax.studies.truth import true_magnitudes

    d = short_dict(sim=2, duration=0.2, events=(0.05, 0.1))
    d["events"][1].update(ramp=0.01, growth="exponential", magnitude=2.0)
    sc = parse_scenario(d)
    names = list(sc.faults)
    j = names.index(d["events"][1]["fault"])
    got = true_magnitudes(sc, names, 2000)[:, j]
    np.testing.assert_allclose(got, _exp_profile(range(2000), 1000, 2.0, 100), atol=1e-14)
    setup = setup_scenario(sc, "uimm")
    steps = np.asarray(setup.plan.event_steps)
    growth = (np.arange(len(names)) == j).astype(int)
    want = fault_breakpoints(*_single(names, j), growth=growth)[0]
    np.testing.assert_array_equal(steps[steps < NEVER][1:], want)  # [0]: valve wear

    seen = {}

    def spy(setup, onset, magnitude, noise, keys, K, dtype, **kw):
        seen.update(kw)
        raise KeyboardInterrupt  # stop before compiling anything

    monkeypatch.setattr(sweep_mod, "batch_inputs", spy)
    with pytest.raises(KeyboardInterrupt):
        sweep_mod.run_sweep(sc, runs=2, methods=["uimm"], fault_free=False)
    np.testing.assert_array_equal(seen["growth"], np.broadcast_to(growth, seen["growth"].shape))
    assert set(seen["ramp"][:, j].tolist()) == {100}  # the batch: 2 runs padded to 16


def _single(names, j):
    """Onset, magnitude and ramp of the last test's air in oil alone."""
    onset = np.full(len(names), -1)
    onset[j] = 1000
    ramp = np.zeros(len(names), np.int64)
    ramp[j] = 100
    return onset, np.where(np.arange(len(names)) == j, 2.0, 1.0), ramp
