"""Screening of uimm-est settings on single cells of benchmarks/faults_unknown_size.py.

Usage (from the repository root, ``PYTHONPATH=src``)::

    python .../session8_pre/screen.py CELLS RUNS TAG [NAME=VALUE ...]

``CELLS`` is a comma list of ``r1s1`` (1 s ramps, sim 1), ``r10s1``, ``sz1``/``sz2``
(abrupt sizes, sim 1/2), ``int1``/``int2`` (intermittent, sim 1/2), ``pap`` (paper); the
cells are those of the benchmark's parts (same scenarios, seed 0, magnitudes 0.3-3).
``NAME=VALUE`` overrides an ``EstSettings`` default.  Writes ``screen_TAG_CELLS_RUNS.json``
here: per cell, the benchmark's summaries.
"""

import argparse
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2]))  # benchmarks/

import faults_unknown_size as fu  # noqa: E402
import uimm_jax.engine.uimm_est as ue  # noqa: E402


def main() -> None:
    cells, runs, tag = sys.argv[1].split(","), int(sys.argv[2]), sys.argv[3]
    d0 = dict(zip(ue.EstSettings._fields, ue.EstSettings.__new__.__defaults__, strict=True))
    for item in sys.argv[4:]:
        k, v = item.split("=")
        d0[k] = type(d0[k])(float(v))
    ue.EstSettings.__new__.__defaults__ = tuple(d0.values())
    args = argparse.Namespace(runs=runs, methods=["uimm-est"], seed=0, batch=128)
    out = {}
    for c in cells:
        t0 = time.process_time()
        if c.startswith(("r", "sz")):
            sim = int(c[-1])
            r = float(c[1:-2]) if c.startswith("r") else 0.0
            a, b = fu.FIRST[sim]
            t2, dur = (1.2, 2.0) if not r else (1.5 + r, 2.5 + 2 * r)
            events = [{"fault": a, "time": 0.5}, {"fault": b, "time": t2}]
            sc = fu._scenario(sim, dur)
            case = {"name": f"sim{sim}", "events": events}
            res = fu._sweep(sc, [case], args, magnitudes=fu.MAGS, ramps=[r], fault_free=False)
        elif c.startswith("int"):
            sim = int(c[-1])
            fault = {1: "leakage", 2: "air_in_oil"}[sim]
            ev = {"fault": fault, "time": [0.5, 1.0], "duration": [2.0, 4.0]}
            case = {"name": f"{fault}-intermittent", "events": [ev]}
            res = fu._sweep(
                fu._scenario(sim, 6.0), [case], args, magnitudes=[1.0], fault_free=False
            )
        else:  # pap
            res = []
            for sim in (1, 2):
                a, b = fu.FIRST[sim]
                ev = [{"fault": a, "time": 1.0}, {"fault": b, "time": 2.5}]
                case = {"name": f"sim{sim}", "events": ev}
                sc = fu._scenario(sim, 4.0)
                res += fu._sweep(sc, [case], args, magnitudes=[1.0], fault_free=True)
        out[c] = res
        line = []
        for s in res:
            det = "/".join(f"{100 * p:.0f}" for p in s["detection_probability"].values())
            dl = "/".join(
                "-" if x is None else f"{1e3 * x:.0f}" for x in s["median_delay_s"].values()
            )
            mare = "/".join(f"{100 * x:.1f}" for x in s.get("magnitude_mare", {}).values())
            line.append(
                f"m{s['magnitude']}: F{s['false_declarations']}/{s.get('false_declarations_all')}"
                f" det{det} iso{100 * s['isolation_accuracy']:.0f} d{dl} mare{mare}"
                f" acc{s['mode_accuracy']:.3f}"
            )
        print(f"[{tag}] {c} ({time.process_time() - t0:.0f}s cpu): " + " | ".join(line), flush=True)
    name = f"screen_{tag}_{'-'.join(cells)}_{runs}.json"
    (HERE / name).write_text(json.dumps(out, default=float))


if __name__ == "__main__":
    main()
