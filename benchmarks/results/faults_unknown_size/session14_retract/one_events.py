"""One run of given events; prints declared faults' estimates around each change (session 14).

Usage (repository root, ``PYTHONPATH=src``):
``one_events.py SIM DURATION SEED 'FAULT@T0[+LEN][~RAMP][*MAG]' ... [-- NAME=VALUE ...]``:
the tuned scenario of ``SIM`` cut to ``DURATION`` s, noise seed ``SEED``, with those events
(a fault from ``T0`` for ``LEN`` s, ramping over ``RAMP`` s, at magnitude ``MAG``).  Prints
the mode probabilities, the declared code, model 0's estimates (each fault's own hypothesis'
while undeclared) and sds every ``STEP`` samples (env, default 5000) and every ``EVERY``
samples (env, default 20) in the ``WIN`` samples (env, default 600) before each change of
the declared set and 100 after each fault's end.
"""

import os
import re
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "session11_ramp2"))
import ramp_false as rf  # noqa: E402

from uimm_jax.studies import run as srun  # noqa: E402


def _event(text):
    m = re.fullmatch(r"(\w+)@([\d.]+)(?:\+([\d.]+))?(?:~([\d.]+))?(?:\*([\d.]+))?", text)
    fault, t0, length, ramp, mag = m.groups()
    ev = {"fault": fault, "time": float(t0), "magnitude": float(mag or 1.0)}
    if length:
        ev["end"] = float(t0) + float(length)
    if ramp:
        ev["ramp"] = float(ramp)
    return ev


def main():
    argv = sys.argv[1:]
    sets = argv[argv.index("--") + 1 :] if "--" in argv else []
    pos = argv[: argv.index("--")] if "--" in argv else argv
    rf._settings(sets)
    sim, duration, seed = int(pos[0]), float(pos[1]), int(pos[2])
    events = [_event(t) for t in pos[3:]]
    rf.DURATION = duration
    sc = rf._scenario(sim, events)
    setup = srun.setup_scenario(sc, "uimm-est")
    key = jax.random.PRNGKey(seed)
    orig = jax.random.PRNGKey
    jax.random.PRNGKey = lambda s: key
    try:
        o = srun.execute_run(setup, srun.filter_measurements)
    finally:
        jax.random.PRNGKey = orig
    mp, dec = o.outputs["mode_probs"], o.outputs["declared"]
    mag, sd = o.outputs["magnitude"], o.outputs["magnitude_sd"]
    st, ev, win = (
        int(os.environ.get(k, v)) for k, v in (("STEP", 5000), ("EVERY", 20), ("WIN", 600))
    )
    dt = float(sc.dt) if hasattr(sc, "dt") else 1e-4
    ends = [int(round(e["end"] / dt)) for e in events if "end" in e]
    ch = list(np.nonzero(np.diff(dec))[0] + 1)
    ks = set(range(0, len(dec), st))
    for c in ch:
        ks |= set(range(max(c - win, 0), c, ev)) | {c - 1, c}
    for e in ends:
        ks |= set(range(e, min(e + 100, len(dec))))
    np.set_printoptions(linewidth=200, suppress=True)
    for k in sorted(ks):
        print(k, np.round(mp[k], 3), dec[k], np.round(mag[k], 4), np.round(sd[k], 4))
    print({k: o.summary[k] for k in ("declarations", "retractions")})
    _ = jnp


if __name__ == "__main__":
    main()
