"""Sweep a ramp cell and trace its false runs (session 11, sim 2's 10 s ramps).

Usage (from the repository root, ``PYTHONPATH=src``):

* ``ramp_false.py sweep SIM TAG MAG [MAG ...] -- NAME=VALUE ...``: the ``ramps`` part's case
  (``RAMP`` s from the environment, default 10; 64 runs, seed 0) at each ``MAG``, uimm-est's
  defaults changed by ``NAME=VALUE`` (checked as ``--set`` is); writes the benchmark's JSON
  (``ramps_<RAMP>_uimm-est_64<TAG>.json`` here, with ``command`` and the false runs) and
  prints, per run with a false declaration, the declaration and retraction steps and the
  final estimates.  ``OUT`` (env) names another folder for the JSON (session 12).
* ``ramp_false.py one SIM MAG RUN -- NAME=VALUE ...``: re-simulates run ``RUN`` of that
  sweep (its noise key) as a single run and prints the mode probabilities, the declared set
  and the estimates every ``STEP`` (env, default 5000) samples and around every change of
  the declared set (window ``K0``..``K1``).
"""

import json
import os
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import uimm_jax.engine.uimm_est as ue  # noqa: E402
from uimm_jax.engine.truth import run_keys  # noqa: E402
from uimm_jax.engine.uimm_est_types import est_settings, est_value_from_text  # noqa: E402
from uimm_jax.scenario.parse import load_scenario, parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402
from uimm_jax.studies import run as srun  # noqa: E402
from uimm_jax.studies.sweep import run_sweep  # noqa: E402

REPO = Path(__file__).resolve().parents[4]
HERE = Path(os.environ.get("OUT", Path(__file__).resolve().parent))  # where sweeps write
FIRST = {1: ("valve_wear", "leakage"), 2: ("valve_wear", "air_in_oil")}
RAMP = float(os.environ.get("RAMP", "10"))
# RAMP=0: the ``sizes`` part's abrupt case (onsets 0.5 / 1.2 s of a 2 s run; session 12)
ONSET2, DURATION = (1.5 + RAMP, 2.5 + 2 * RAMP) if RAMP else (1.2, 2.0)


def _settings(items):
    values = {}
    for item in items:
        name, _, text = item.partition("=")
        values[name] = est_value_from_text(name, text)
    ue.EstSettings.__new__.__defaults__ = tuple(est_settings(values, name="--set"))


def _scenario(sim, events=None):
    d = scenario_to_dict(load_scenario(REPO / "scenarios" / f"paper_sim{sim}_tuned.toml"))
    d["duration"] = DURATION
    for e in d["events"]:
        e["time"] = min(e["time"], d["duration"] / 2)
    if events is not None:
        d["events"] = events
    return parse_scenario(d, source=f"paper_sim{sim}_tuned")


def run_cells(sim, mags, runs=64, seed=0):
    """The ``ramps`` part's case of ``sim`` at each magnitude: 64 runs, seed 0 (a sweep result)."""
    a, b = FIRST[sim]
    case = {
        "name": f"sim{sim}",
        "events": [{"fault": a, "time": 0.5}, {"fault": b, "time": ONSET2}],
    }
    return run_sweep(
        _scenario(sim),
        runs=runs,
        methods=["uimm-est"],
        cases=[case],
        seed=seed,
        batch=128,
        magnitudes=mags,
        ramps=[RAMP],
        fault_free=False,
    )


def sweep(sim, tag, mags, sets):
    t0 = time.perf_counter()
    res = run_cells(sim, mags)
    drop = ("confusion", "state_rmse", "health", "detection_probability_ci")
    out = []
    for cell, s in zip(res.cells, res.summaries, strict=True):
        c = cell.index
        fd = res.false_declared()[c]
        runs = []
        for r in np.nonzero(fd.any(-1))[0]:
            est = {
                k: np.asarray(res.estimates[k][c, r]).tolist()
                for k in ("retract_step", "magnitude", "magnitude_sd")
            }
            runs.append(
                {
                    "run": int(r),
                    "false": [res.faults[f] for f in np.nonzero(fd[r])[0]],
                    "decl_step": res.decl_step[c, r].tolist(),
                    "onset_step": res.onset_step[c, r].tolist(),
                    **est,
                }
            )
            print(f"mag {cell.magnitude} run {r}: {runs[-1]}", flush=True)
        out.append(
            {k: v for k, v in s.items() if k not in drop}
            | {"false_runs": runs, "runtime_s": res.runtime_s}
        )
        print(
            f"mag {s['magnitude']}: false {s['false_declarations']} "
            f"iso {s['isolation_accuracy']:.3f} det {s['detections']}",
            flush=True,
        )
    doc = {
        f"sim{sim}": out,
        "faults": list(res.faults),
        "command": " ".join(["RAMP=" + str(RAMP), "python", "ramp_false.py", *sys.argv[1:]]),
        "wall_s": time.perf_counter() - t0,
    }
    (HERE / f"ramps_{RAMP}_uimm-est_64{tag}.json").write_text(
        json.dumps(doc, indent=1, default=float)
    )


def one(sim, mag, r):
    a, b = FIRST[sim]
    ramp = {"ramp": RAMP} if RAMP else {}
    ev = [
        {"time": 0.5, "fault": a, "magnitude": mag, **ramp},
        {"time": ONSET2, "fault": b, "magnitude": mag, **ramp},
    ]
    sc = _scenario(sim, ev)
    setup = srun.setup_scenario(sc, "uimm-est")
    key = jnp.asarray(run_keys(int(os.environ.get("SEED", "0")), 64)[0][r])  # SEED: session 23
    orig = jax.random.PRNGKey
    jax.random.PRNGKey = lambda s: key  # simulate_scenario's key: the sweep's noise key of run r
    try:
        o = srun.execute_run(setup, srun.filter_measurements)
    finally:
        jax.random.PRNGKey = orig
    mp, dec = o.outputs["mode_probs"], o.outputs["declared"]
    st, k0, k1 = (
        int(os.environ.get(k, v)) for k, v in (("STEP", 5000), ("K0", 0), ("K1", len(dec)))
    )
    ch = np.nonzero(np.diff(dec))[0] + 1
    ks = sorted(set(range(k0, k1, st)) | {c + j for c in ch for j in (-1, 0) if k0 <= c < k1})
    np.set_printoptions(linewidth=200)
    for k in ks:
        print(
            k,
            np.round(mp[k], 3),
            dec[k],
            np.round(o.outputs["magnitude"][k], 3),
            np.round(o.outputs["magnitude_sd"][k], 4),
        )
    print({k: o.summary[k] for k in ("declarations", "retractions")})
    if os.environ.get("SAVE"):
        np.savez(
            os.environ["SAVE"],
            mode_probs=mp,
            declared=dec,
            magnitude=o.outputs["magnitude"],
            magnitude_sd=o.outputs["magnitude_sd"],
        )


def main():
    argv = sys.argv[1:]
    sets = argv[argv.index("--") + 1 :] if "--" in argv else []
    pos = argv[: argv.index("--")] if "--" in argv else argv
    _settings(sets)
    if pos[0] == "sweep":
        sweep(int(pos[1]), pos[2], [float(m) for m in pos[3:]], sets)
    else:
        one(int(pos[1]), float(pos[2]), int(pos[3]))


if __name__ == "__main__":
    main()
