"""The long-run test's seed (session 24).

Usage (repository root, ``PYTHONPATH=src``): ``seed_find.py DURATION K0 K1``: sim 2 with valve
wear at 0.5 s and air in oil at 11.5 s, both at 2 over 10 s ramps, runs of ``DURATION`` s at
seeds ``K0 .. K1 - 1`` through ``run_scenario``, with ``end_prior`` 0 and 1e-6; prints each
seed's retractions and declared sizes with their intervals.
"""

import json
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import uimm_jax  # noqa: E402
from uimm_jax.scenario.parse import parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402

SIM2 = Path(__file__).resolve().parents[4] / "scenarios" / "paper_sim2_tuned.toml"


def main():
    d = scenario_to_dict(uimm_jax.load_scenario(SIM2))
    d["duration"] = float(sys.argv[1])
    d["events"] = [
        {"fault": "valve_wear", "time": 0.5, "magnitude": 2.0, "ramp": 10.0},
        {"fault": "air_in_oil", "time": 11.5, "magnitude": 2.0, "ramp": 10.0},
    ]
    for k in range(int(sys.argv[2]), int(sys.argv[3])):
        out = {}
        for p in (0.0, 1e-6):
            d["filter"]["est"]["end_prior"] = p
            s = uimm_jax.run_scenario(parse_scenario(d), seed=k).summary
            ret = [(x["fault"], round(x["time"], 3)) for x in s["retractions"]]
            dec = [(x["fault"], x["magnitude"], x["magnitude_ci"]) for x in s["declarations"]]
            out[p] = (ret, dec)
        print(k, json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
