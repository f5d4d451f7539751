"""What the per-step ``nis`` outputs cost the run command: ``filter_chunk`` on the tuned
sim 1 (uimm-est and uimm) with the default outputs against the same without
``nis_channels`` (session 17) and without both ``nis`` outputs (session 16: without
``nis``), interleaved in one process, process CPU time, median of REPEATS.

Usage (repository root): ``python benchmarks/results/innovation_check/cost_nis.py [REPEATS]``.
"""

import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from uimm_jax.engine.scan import ESTIMATE_OUTPUTS, FILTER_OUTPUTS, filter_chunk  # noqa: E402
from uimm_jax.scenario.parse import load_scenario  # noqa: E402
from uimm_jax.studies.run import scenario_inputs, setup_scenario, simulate_scenario  # noqa: E402

N = 200_000


def main():
    repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 7
    sc = load_scenario("scenarios/paper_sim1_tuned.toml")
    for method in ("uimm-est", "uimm"):
        setup = setup_scenario(sc, method)
        truth = simulate_scenario(setup, 0)
        ys = jnp.asarray(truth["y"][:N])
        us = jnp.asarray(scenario_inputs(sc, N))
        extra = ESTIMATE_OUTPUTS if method == "uimm-est" else ()
        keys = {"default": FILTER_OUTPUTS + extra}
        keys["without nis_channels"] = tuple(k for k in keys["default"] if k != "nis_channels")
        keys["without nis"] = tuple(k for k in keys["default"] if k not in ("nis", "nis_channels"))
        times = {k: [] for k in keys}
        for _ in range(repeats):
            for name, ks in keys.items():
                args = (setup.diagnoser, setup.params, setup.init_state, 0, (us, ys), ks)
                f = lambda args=args: filter_chunk(*args)  # noqa: E731
                jax.block_until_ready(f())  # compiled (cached after the first)
                t0 = time.process_time()
                jax.block_until_ready(f())
                times[name].append((time.process_time() - t0) / N * 1e6)
        med = {k: float(np.median(v)) for k, v in times.items()}
        base = med["without nis"]
        print(
            f"{method}: default {med['default']:.3f} us/step, without nis_channels "
            f"{med['without nis_channels']:.3f}, without both {base:.3f}; ratios "
            f"{med['default'] / base:.3f}, {med['without nis_channels'] / base:.3f}"
        )


if __name__ == "__main__":
    main()
