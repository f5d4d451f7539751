"""Which runs of an abrupt ``sizes`` cell declare an absent fault (session 10).

Usage: ``[RAMP=r] false_sizes.py SIM MAG [NAME=VALUE ...]``.

The ``sizes`` part's case (64 runs, seed 0) at magnitude ``MAG``, uimm-est defaults changed
by ``NAME=VALUE`` (a per-fault value as ``v1,v2,v3``); with ``RAMP`` (s, default 0) the
``ramps`` part's case of that ramp.  Prints, per run with a false declaration, the false
faults, every fault's first declaration step and its last retraction step.
"""

import importlib.util
import os
import sys
from pathlib import Path

import jax
import numpy as np

import uimm_jax.engine.uimm_est as ue
from uimm_jax.studies.sweep import run_sweep


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    path = Path(__file__).resolve().parents[3] / "faults_unknown_size.py"
    spec = importlib.util.spec_from_file_location("fus", path)
    fus = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fus)
    sim, mag = int(sys.argv[1]), float(sys.argv[2])
    d = dict(zip(ue.EstSettings._fields, ue.EstSettings.__new__.__defaults__, strict=True))
    for item in sys.argv[3:]:
        k, v = item.split("=")
        d[k] = tuple(float(x) for x in v.split(",")) if "," in v else type(d[k])(float(v))
    ue.EstSettings.__new__.__defaults__ = tuple(d.values())
    a, b = fus.FIRST[sim]
    ramp = float(os.environ.get("RAMP", "0"))
    t2, dur = (1.5 + ramp, 2.5 + 2 * ramp) if ramp else (1.2, 2.0)
    case = {"name": f"sim{sim}", "events": [{"fault": a, "time": 0.5}, {"fault": b, "time": t2}]}
    res = run_sweep(
        fus._scenario(sim, dur),
        runs=64,
        methods=["uimm-est"],
        cases=[case],
        seed=0,
        batch=128,
        magnitudes=[mag],
        ramps=[ramp],
        fault_free=False,
    )
    c = [c.index for c in res.cells if c.case == f"sim{sim}"][0]
    fd = res.false_declared()[c]
    for r in np.nonzero(fd.any(-1))[0]:
        false = [res.faults[f] for f in np.nonzero(fd[r])[0]]
        ret = res.estimates["retract_step"][c, r].tolist()
        print(f"sim{sim} run {r}: false {false}, decl_step {res.decl_step[c, r].tolist()}")
        print(f"  retract_step {ret}")


if __name__ == "__main__":
    main()
