"""Which runs declare an absent fault, and when: ``false_runs.py MAG [NAME=VALUE ...]``.

The 1 s ramp cells of ``faults_unknown_size.py ramps`` (64 runs, seed 0, both sims) at
magnitude ``MAG``, with the uimm-est defaults changed by ``NAME=VALUE``.  Prints, per run
with a false declaration, the false faults and every fault's first declaration step.
"""

import importlib.util
import sys
from pathlib import Path

import numpy as np

import uimm_jax.engine.uimm_est as ue
from uimm_jax.studies.sweep import run_sweep


def main() -> None:
    path = Path(__file__).resolve().parents[3] / "faults_unknown_size.py"
    spec = importlib.util.spec_from_file_location("fus", path)
    fus = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fus)
    mag = float(sys.argv[1])
    d = dict(zip(ue.EstSettings._fields, ue.EstSettings.__new__.__defaults__, strict=True))
    for item in sys.argv[2:]:
        k, v = item.split("=")
        d[k] = type(d[k])(float(v))
    ue.EstSettings.__new__.__defaults__ = tuple(d.values())
    for sim in (1, 2):
        a, b = fus.FIRST[sim]
        case = {
            "name": f"sim{sim}",
            "events": [{"fault": a, "time": 0.5}, {"fault": b, "time": 2.5}],
        }
        res = run_sweep(
            fus._scenario(sim, 4.5),
            runs=64,
            methods=["uimm-est"],
            cases=[case],
            seed=0,
            batch=128,
            magnitudes=[mag],
            ramps=[1.0],
            fault_free=False,
        )
        c = [c.index for c in res.cells if c.case == f"sim{sim}"][0]
        fd = res.false_declared()[c]
        for r in np.nonzero(fd.any(-1))[0]:
            false = [res.faults[f] for f in np.nonzero(fd[r])[0]]
            print(f"sim{sim} run {r}: false {false}, decl_step {res.decl_step[c, r].tolist()}")


if __name__ == "__main__":
    main()
