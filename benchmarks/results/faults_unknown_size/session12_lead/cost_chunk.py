# ruff: noqa: E402, E501, E702, B023
"""The cost command's one-run loop (sim 1, 1 s, both onsets at 0.5 s) at chunk 2000 and the default chunk."""

import sys
import time

import jax

import uimm_jax  # noqa

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
import faults_unknown_size as fus
from uimm_jax.studies.run import filter_measurements, setup_scenario, simulate_scenario

sc = fus._scenario(1, 1.0)
setups = {m: setup_scenario(sc, m) for m in ("uimm", "uimm-est")}
truth = simulate_scenario(setups["uimm"], 0)
N1 = truth["y"].shape[0]
t = {(m, c): [] for m in setups for c in (2000, N1)}
for m, c in t:
    filter_measurements(setups[m], truth["y"], truth["u"], chunk=c)
for _ in range(int(sys.argv[1])):
    for m, c in t:
        t0 = time.process_time()
        filter_measurements(setups[m], truth["y"], truth["u"], chunk=c)
        t[(m, c)].append(1e6 * (time.process_time() - t0) / N1)
for c in (2000, N1):
    a, b = sorted(t[("uimm", c)]), sorted(t[("uimm-est", c)])
    print(
        f"chunk {c}: uimm {a}, uimm-est {b}; best {b[0] / a[0]:.2f}x, median {b[len(b) // 2] / a[len(a) // 2]:.2f}x"
    )
