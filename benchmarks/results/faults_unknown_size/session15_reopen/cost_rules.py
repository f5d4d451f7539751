"""What session 15's rules cost per step: uimm-est with the defaults against the defaults
with ``reopen_old``, ``settle_creep`` and ``retract_rise`` off and ``retract_young`` at
session 14's 10000, interleaved in one process (the ``cost`` part's data and timers).

Usage (repository root): ``python .../session15_reopen/cost_rules.py [REPEATS] [-- NAME=VALUE
...]``; with ``--`` the defaults are timed against the defaults changed so (session 16:
``-- floor_z=0``).
"""

import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2]))
sys.path.insert(0, str(HERE.parent / "session11_ramp2"))
import ramp_false  # noqa: E402

import faults_unknown_size as fus  # noqa: E402
from uimm_jax.studies.run import setup_scenario, simulate_scenario  # noqa: E402

OFF = ["reopen_old=0", "settle_creep=0", "retract_rise=0", "retract_young=10000"]


def main():
    argv = sys.argv[1:]
    pos = argv[: argv.index("--")] if "--" in argv else argv
    sets = argv[argv.index("--") + 1 :] if "--" in argv else OFF
    new, old = ("session 15", "session 14") if sets is OFF else ("defaults", " ".join(sets))
    repeats = int(pos[0]) if pos else 7
    sc = fus._scenario(1, 1.0)
    setups = {new: setup_scenario(sc, "uimm-est")}
    ramp_false._settings(sets)
    setups[old] = setup_scenario(sc, "uimm-est")
    truth = simulate_scenario(setup_scenario(sc, "uimm"), 0)
    one, batch = fus.cost_timings(setups, truth, repeats)  # the cost part's timers
    for name, d in (("one run, us/step", one), ("64 runs, us per run-step", batch)):
        med = {m: float(np.median(v)) for m, v in d.items()}
        print(
            f"{name}: "
            + ", ".join(f"{m} {med[m]:.3f} ({min(d[m]):.3f}-{max(d[m]):.3f})" for m in d)
            + f"; ratio {med[new] / med[old]:.3f}"
        )


if __name__ == "__main__":
    main()
