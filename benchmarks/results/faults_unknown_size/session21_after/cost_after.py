# ruff: noqa  (scratch of session 21: see README.md)
"""The cost of ``retract_after``: ``faults_unknown_size.py``'s cost timings (one run of 1e4
steps; 64 runs of 4000 steps with the truth) of the fixed-size UIMM, uimm-est on the
defaults (``retract_after = 4000``) and uimm-est with ``retract_after = 0``, interleaved in
one process.  Usage (repository root): ``python .../session21_after/cost_after.py [REPEATS]
[NAME=VALUE]``; ``NAME=VALUE`` (session 22) times uimm-est with that setting instead of
``retract_after=0`` (e.g. ``drift_walk=3.0``)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path("benchmarks").resolve()))
import jax

jax.config.update("jax_enable_x64", True)
import numpy as np

import faults_unknown_size as fu
from uimm_jax.engine.uimm_est_types import est_value_from_text
from uimm_jax.scenario.parse import parse_scenario
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.studies.run import setup_scenario, simulate_scenario

sc = fu._scenario(1, 1.0)
d = scenario_to_dict(sc)
setting, _, value = (sys.argv[2] if len(sys.argv) > 2 else "retract_after=0").partition("=")
d["filter"]["est"][setting] = est_value_from_text(setting, value)
setups = {
    "uimm": setup_scenario(sc, "uimm"),
    "uimm-est": setup_scenario(sc, "uimm-est"),
    "uimm-est_set": setup_scenario(parse_scenario(d), "uimm-est"),
}
truth = simulate_scenario(setups["uimm"], 0)
single, batch = fu.cost_timings(setups, truth, int(sys.argv[1]) if len(sys.argv) > 1 else 5)
for name, t in (("one run, us/step", single), ("64 runs, us/run-step", batch)):
    med = {m: float(np.median(v)) for m, v in t.items()}
    print(name, {m: round(v, 3) for m, v in med.items()},
          "defaults/(%s=%s) = %.3f" % (setting, value, med["uimm-est"] / med["uimm-est_set"]),
          "uimm-est/uimm = %.2f" % (med["uimm-est"] / med["uimm"]))
