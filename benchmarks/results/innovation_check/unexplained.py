"""The innovation check's ``unexplained`` spells on runs the bank explains and on runs it
does not (session 17): the paper's scenarios at full length with both methods, faults of
other sizes and ramps, a fault ending, and the truth's measurement noise doubled.

Usage (repository root): ``python benchmarks/results/innovation_check/unexplained.py``
(about 3 minutes).
"""

import warnings

import jax

jax.config.update("jax_enable_x64", True)

from uimm_jax.scenario.parse import load_scenario, parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402
from uimm_jax.studies.run import (  # noqa: E402
    execute_run,
    filter_measurements,
    run_scenario,
    setup_scenario,
)


def scenario(sim, method, duration=None, events=None, noise_x=1.0):
    d = scenario_to_dict(load_scenario(f"scenarios/paper_sim{sim}_tuned.toml"))
    if duration is not None:
        d["duration"] = duration
    if events is not None:
        d["events"] = events
    d["filter"]["method"] = method
    if method != "uimm-est":
        d["filter"].pop("est", None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sc = parse_scenario(d, source=f"paper_sim{sim}_tuned")
        d["noise"]["measurement"] = [v * noise_x**2 for v in d["noise"]["measurement"]]
        truth = parse_scenario(d, source=f"paper_sim{sim}_tuned")
    return sc, truth


def show(label, sc, truth=None):
    if truth is None:
        s = run_scenario(sc).summary
    else:
        st = setup_scenario(sc)
        s = execute_run(st, filter_measurements, truth_setup=setup_scenario(truth), seed=0).summary
    ic = s["innovation_check"]
    decl = ", ".join(
        f"{x['fault']} {x['time']:.3f}{'' if x['correct'] else ' FALSE'}" for x in s["declarations"]
    )
    spells = "; ".join(
        f"{x['start']:.3f}-{x['end']:.3f} s (peak {x['peak_nis']:.3g})" for x in ic["unexplained"]
    )
    print(
        f"{label}: mean {ic['mean_nis_per_channel']:.3f}; declared {decl or '-'}; "
        f"unexplained: {spells or 'none'}"
    )


def main() -> None:
    for sim in (1, 2):
        for method in ("uimm-est", "uimm"):
            show(f"sim {sim} full length, {method}", scenario(sim, method)[0])
    for method in ("uimm", "uimm-est"):
        for mag in (0.5, 3.0):
            ev = [{"time": 3.0, "fault": "valve_wear", "magnitude": mag}]
            show(f"sim 1, valve wear x{mag} at 3 s, {method}", scenario(1, method, 10.0, ev)[0])
    ramp = [
        {"time": 1.0, "fault": "valve_wear", "magnitude": 3.0, "ramp": 10.0},
        {"time": 6.0, "fault": "air_in_oil", "magnitude": 3.0, "ramp": 10.0},
    ]
    show("sim 2, 10 s ramps to 3, uimm-est", scenario(2, "uimm-est", 20.0, ramp)[0])
    ends = [{"time": 2.0, "fault": "leakage", "magnitude": 1.0, "end": 5.0}]
    show("sim 1, leakage from 2 s to 5 s, uimm-est", scenario(1, "uimm-est", 8.0, ends)[0])
    show("sim 1, leakage from 2 s to 5 s, uimm", scenario(1, "uimm", 8.0, ends)[0])
    sc, truth = scenario(1, "uimm-est", 5.0, [], noise_x=2.0)
    show("sim 1 fault-free, measurement noise sd x2, uimm-est", sc, truth)


if __name__ == "__main__":
    main()
