"""Scenarios and truth events of ``bench_model_count.py`` (the F-fault banks and its cases)."""

from __future__ import annotations

import numpy as np

from _common import REPO

BASE_SCENARIO = REPO / "scenarios" / "paper_sim1_tuned.toml"


def fault_names() -> list[str]:
    """The hydraulic actuator's 10 library faults, paper's three first."""
    from uimm_jax.plants.hydraulic_actuator import HYDRAULIC_ACTUATOR

    return list(HYDRAULIC_ACTUATOR.fault_library)


def build_scenario(
    num_faults: int,
    duration: float,
    events=(),
    name: str | None = None,
    filter_overrides: dict | None = None,
):
    """The tuned paper scenario with the first ``num_faults`` library faults as the bank.

    Args:
        num_faults: F, the bank's faults (the library's first F, library values).
        duration: run length in s.
        events: truth events, dicts with ``time``, ``fault``, ``magnitude``.
        name: scenario name (default ``multifault-F<F>``).
        filter_overrides: ``[filter]`` entries to replace (``stay``, ``decision``).

    Returns:
        A validated :class:`~uimm_jax.Scenario` (``stay`` from the base
        scenario, default initial mode probabilities).
    """
    from uimm_jax.scenario.parse import load_scenario, parse_scenario
    from uimm_jax.scenario.write import scenario_to_dict

    names = fault_names()
    d = scenario_to_dict(load_scenario(BASE_SCENARIO))
    d["name"] = name or f"multifault-F{num_faults}"
    d["duration"] = float(duration)
    d["faults"] = {n: {} for n in names[:num_faults]}
    d.pop("sweep", None)
    if events:
        d["events"] = [dict(e) for e in events]
    else:
        d.pop("events", None)
    flt = d["filter"]
    flt.pop("transition", None)
    flt.pop("initial_mode_probs", None)
    flt.setdefault("stay", 0.9999)
    flt.update(filter_overrides or {})
    return parse_scenario(d, source=f"bench_model_count F={num_faults}")


def draw_events(
    num_faults: int,
    k: int,
    duration: float,
    rng: np.random.Generator,
    *,
    margin: float = 1.0,
    min_gap: float = 1.0,
) -> list[dict]:
    """Draw k of the first ``num_faults`` library faults in a random order at random onsets.

    The faults are ``rng.permutation(num_faults)[:k]`` (distinct, random order).  The
    onsets are uniform over the sorted k-tuples in ``[margin, duration - margin]`` whose
    gaps are all at least ``min_gap``: ``t_i = margin + u_(i) + i * min_gap`` with ``u_(i)``
    the sorted uniform draws on ``[0, duration - 2 margin - (k - 1) min_gap]``; rounded to
    1 ms.

    Args:
        num_faults: F, the size of the fault library drawn from.
        k: number of faults (1 <= k <= F).
        duration: run length in s.
        rng: the generator (seed it for reproducible runs).
        margin: no onset closer than this to the start or the end, s.
        min_gap: minimum time between two onsets, s.

    Returns:
        Event dicts (``time``, ``fault``, ``magnitude`` = 1), sorted by time.
    """
    if not 1 <= k <= num_faults:
        raise ValueError(f"k must be in [1, {num_faults}], got {k}")
    slack = duration - 2.0 * margin - (k - 1) * min_gap
    if slack <= 0:
        raise ValueError(f"{k} onsets {min_gap} s apart do not fit in {duration} s")
    names = fault_names()
    order = rng.permutation(num_faults)[:k]
    u = np.sort(rng.uniform(0.0, slack, k))
    times = np.round(margin + u + min_gap * np.arange(k), 3)
    return [
        {"time": float(t), "fault": names[int(j)], "magnitude": 1.0}
        for t, j in zip(times, order, strict=True)
    ]


CASES = {
    "main": "k = min(F, --faults-per-run) faults in a random order, onsets >= --min-gap apart",
    "simultaneous": "2 faults with the same onset (uniform in [1 s, duration - 1 s])",
    "loose": (
        "as main with k = min(F, 2), but the paper's loose rule: stay 0.9 (eq. 37's "
        "diagonal), threshold 0.9 (eq. 29), hold 1"
    ),
}
LOOSE_FILTER = {"stay": 0.9, "decision": {"threshold": 0.9, "hold": 1}}


def truth_seed(seed: int, num_faults: int, run: int, case: int) -> int:
    """Seed of the truth noise of one run: ``SeedSequence([seed, F, run, case])``."""
    return int(np.random.SeedSequence([seed, num_faults, run, case]).generate_state(1)[0])


def case_events(case: str, num_faults: int, run: int, duration: float, args) -> list[dict]:
    """The truth events of run ``run`` of a case (see :data:`CASES`).

    ``main`` draws with ``np.random.default_rng([seed, F, run])``; the stress cases
    with ``np.random.default_rng([seed, F, run, 1 or 2])``.
    """
    if case == "main":
        rng = np.random.default_rng([args.seed, num_faults, run])
        k = min(num_faults, args.faults_per_run)
        return draw_events(num_faults, k, duration, rng, margin=args.margin, min_gap=args.min_gap)
    if case == "simultaneous":
        rng = np.random.default_rng([args.seed, num_faults, run, 1])
        names = fault_names()
        pair = rng.permutation(num_faults)[:2]
        t = float(np.round(rng.uniform(1.0, duration - 1.0), 3))
        return [{"time": t, "fault": names[int(j)], "magnitude": 1.0} for j in pair]
    if case == "loose":
        rng = np.random.default_rng([args.seed, num_faults, run, 2])
        return draw_events(num_faults, min(num_faults, 2), duration, rng, margin=1.0, min_gap=1.0)
    raise ValueError(f"unknown case {case!r}")


def setup(num_faults: int, method: str, duration: float, events=(), filter_overrides=None):
    """The :class:`~uimm_jax.studies.run.RunSetup` of :func:`build_scenario`'s scenario."""
    from uimm_jax.studies import run

    sc = build_scenario(num_faults, duration, events, filter_overrides=filter_overrides)
    return run.setup_scenario(sc, method)
