"""How much valve wear's onset under a declared air in oil shows in the measurements (session 16).

Simulates sim 2's tuned scenario (2 s) without noise, air in oil at 0.5 s, with and without
valve wear at 1.2 s, both at magnitude MAG, and prints per channel the sum of ``dy^2 / R``
(the information a filter that knew everything else would have, in nats x 2) over the
first 100 and 1000 samples after the onset and over the 0.8 s left.

Usage (repository root): ``python .../session16_floor_z/observability.py [MAG ...]``.
"""

import sys
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[4] / "tests"))
from _robustness_helpers import short_dict  # noqa: E402
from uimm_jax.scenario.parse import parse_scenario  # noqa: E402
from uimm_jax.studies.run import setup_scenario, simulate_scenario  # noqa: E402

K0 = 12000  # valve wear's onset (1.2 s)


def outputs(mag, with_valve_wear):
    d = short_dict(2, duration=2.0, events=(0.5, 1.2))
    d["noise"]["process"] = [1e-30] * 3
    d["noise"]["measurement"] = [1e-30] * 3
    d["events"] = [{"fault": "air_in_oil", "time": 0.5, "magnitude": mag}]
    if with_valve_wear:
        d["events"].append({"fault": "valve_wear", "time": 1.2, "magnitude": mag})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return simulate_scenario(setup_scenario(parse_scenario(d)), 0)["y"]


def main():
    R = np.array(short_dict(2)["noise"]["measurement"], np.float64)
    for mag in [float(a) for a in sys.argv[1:]] or [1.0, 3.0]:
        dy = outputs(mag, True) - outputs(mag, False)
        info = [np.round((dy[K0 : K0 + w] ** 2 / R).sum(0), 3).tolist() for w in (100, 1000, 8000)]
        print(
            f"magnitude {mag}: sum of dy^2/R per channel, 100 samples {info[0]}, "
            f"1000 samples {info[1]}, 0.8 s {info[2]}"
        )


if __name__ == "__main__":
    main()
