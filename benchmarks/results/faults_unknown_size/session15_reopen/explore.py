"""Cells beyond the acceptance list, on the defaults (session 15): how the size-estimating
UIMM does on faults the issue's cells do not draw.

Usage (repository root): ``python .../session15_reopen/explore.py PART [RUNS]`` (the path
under ``benchmarks/results/faults_unknown_size/``), with ``PART`` one of

* ``order``: sim 1 with the faults in the other order (leakage at 0.5 s, valve wear at
  1.2 s), abrupt, magnitudes 0.5, 1, 3 (2 s runs);
* ``order2``: the same at 0.3 and 2, and sim 2 with air in oil at 0.5 s and valve wear at
  1.2 s at 0.5, 1, 3;
* ``three``: all three faults of the actuator, valve wear at 0.5 s, leakage at 1.2 s, air in
  oil at 1.9 s, abrupt, magnitudes 0.5, 1, 2 (3 s runs; the bank of sim 1's file);
* ``noise``: sim 1's and sim 2's abrupt cells at magnitude 1 with the truth's noise 2x and
  0.5x (2 s runs);
* ``slow``: sim 1's and sim 2's ramps of 30 s at magnitudes 1 and 3 (62.5 s runs);
* ``ends``: valve wear from 0.5 s to 6 s, abrupt, while the second fault grows from 3 s
  over 10 s, magnitudes 1 and 3 (15 s runs): an old fault that ends while another grows;
* ``ends_long``: the same with valve wear ending at 12 s and the second fault growing
  from 3 s over 20 s (30 s runs).

Writes ``explore_<PART>_<RUNS><TAG>.json`` here (the sweep summaries, as the benchmark's
files) and prints one line per cell.  ``... PART RUNS -- NAME=VALUE ...`` changes
uimm-est's defaults (as the benchmark's ``--set``); the environment's ``SIMS`` (default
``1 2``) picks the sims and ``TAG`` names the file.
"""

import json
import os
import sys
import time
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

from uimm_jax.scenario.parse import load_scenario, parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402
from uimm_jax.studies.sweep import run_sweep  # noqa: E402

REPO = Path(__file__).resolve().parents[4]
HERE = Path(__file__).resolve().parent
DROP = ("confusion", "state_rmse", "health", "detection_probability_ci")


def scenario(sim, duration):
    d = scenario_to_dict(load_scenario(REPO / "scenarios" / f"paper_sim{sim}_tuned.toml"))
    d["duration"] = duration
    for i, e in enumerate(d["events"]):  # replaced by the cases; kept apart
        e["time"] = duration * (i + 1) / (len(d["events"]) + 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return parse_scenario(d, source=f"paper_sim{sim}_tuned (shortened to {duration} s)")


def case(name, *events):
    return {"name": name, "events": [{"fault": f, "time": t} for f, t in events]}


ENDS = {"ends": (5.5, 10.0, 15.0), "ends_long": (11.5, 20.0, 30.0)}
"""Valve wear's length (s), the second fault's ramp (s) and the run's duration (s)."""


def cells(part):
    if part == "order":
        yield (
            1,
            2.0,
            [case("leak-first", ("leakage", 0.5), ("valve_wear", 1.2))],
            {"magnitudes": [0.5, 1.0, 3.0]},
        )
    elif part == "order2":  # the other magnitudes, and sim 2 with air in oil first
        yield (
            1,
            2.0,
            [case("leak-first", ("leakage", 0.5), ("valve_wear", 1.2))],
            {"magnitudes": [0.3, 2.0]},
        )
        yield (
            2,
            2.0,
            [case("air-first", ("air_in_oil", 0.5), ("valve_wear", 1.2))],
            {"magnitudes": [0.5, 1.0, 3.0]},
        )
    elif part == "three":
        ev = (("valve_wear", 0.5), ("leakage", 1.2), ("air_in_oil", 1.9))
        yield 1, 3.0, [case("three", *ev)], {"magnitudes": [0.5, 1.0, 2.0]}
    elif part == "noise":
        for sim, b in ((1, "leakage"), (2, "air_in_oil")):
            c = case(f"sim{sim}", ("valve_wear", 0.5), (b, 1.2))
            yield sim, 2.0, [c], {"magnitudes": [1.0], "noise_scales": [0.5, 2.0]}
    elif part == "slow":
        for sim, b in ((1, "leakage"), (2, "air_in_oil")):
            c = case(f"sim{sim}", ("valve_wear", 0.5), (b, 31.5))
            yield sim, 62.5, [c], {"magnitudes": [1.0, 3.0], "ramps": [30.0]}
    elif part in ENDS:  # an old fault ends while another still grows
        length, ramp, dur = ENDS[part]
        for sim, b in ((1, "leakage"), (2, "air_in_oil")):
            ev = [{"fault": "valve_wear", "time": 0.5, "duration": length}]
            ev.append({"fault": b, "time": 3.0, "ramp": ramp})
            yield sim, dur, [{"name": f"sim{sim}-{part}", "events": ev}], {"magnitudes": [1.0, 3.0]}
    else:
        raise SystemExit(
            f"unknown part {part!r}: order, three, noise, slow, ends, ends_long or order2"
        )


def main():
    part = sys.argv[1]
    runs = int(sys.argv[2]) if len(sys.argv) > 2 else 64
    sets = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else []
    sims = [int(s) for s in os.environ.get("SIMS", "1 2").split()]
    if sets:  # uimm-est's defaults changed, as the benchmark's --set (session 11's helper)
        sys.path.insert(0, str(HERE.parent / "session11_ramp2"))
        import ramp_false

        ramp_false._settings(sets)
    out, t0 = [], time.perf_counter()
    for sim, dur, cases, kw in cells(part):
        if sim not in sims:
            continue
        res = run_sweep(
            scenario(sim, dur),
            runs=runs,
            methods=["uimm-est"],
            cases=cases,
            fault_free=False,
            seed=0,
            **kw,
        )
        for s in res.summaries:
            s = {k: v for k, v in s.items() if k not in DROP}
            out.append(s)
            if s.get("retraction_probability"):
                print(f"  retractions {s['retraction_probability']} {s['retraction_delay_s']}")
            cov = {f: round(v, 3) for f, v in (s.get("magnitude_coverage") or {}).items()}
            mare = {f: round(v, 4) for f, v in (s.get("magnitude_mare") or {}).items()}
            print(
                f"sim{sim} {s['case']} mag {s['magnitude']} ramp {s.get('ramp')} noise "
                f"{s.get('noise_scale')}: false runs {s['runs_with_false_declaration']}, "
                f"detected {s['detection_probability']}, isolated {s['isolation_accuracy']:.3f}, "
                f"median delay {s['median_delay_s']}, MARE {mare}, coverage {cov}, "
                f"wrong retractions {s.get('wrong_retractions')}, mode accuracy "
                f"{s['mode_accuracy']:.4f}",
                flush=True,
            )
    doc = {
        part: out,
        "command": " ".join(["python", *sys.argv]),
        "wall_s": time.perf_counter() - t0,
    }
    tag = os.environ.get("TAG", "")
    path = HERE / f"explore_{part}_{runs}{tag}.json"
    path.write_text(json.dumps(doc, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
