"""Sweep throughput on the default device (a GPU when one is there), float64 and float32.

Called by ``benchmarks/gpu_check.sh``; prints a Markdown table (and ``--json`` writes it):

* the sweep kernel (:func:`uimm_jax.studies.sweep.run_batch`: truth + UIMM + metrics,
  nothing per step kept beyond a chunk) on one batch of 1e3, 1e4 and 1e5 runs of 1e5
  samples of the paper's simulation 1 (valve wear at 30 % of the run, leakage at 60 %),
  the runs sharded over every local device;
* one 1e6-sample run of ``scenarios/paper_sim1_tuned.toml`` by the single-run path
  (``run_scenario``, ``run_scenario_float32`` for float32: simulate, then filter).

float32 runs the scaled scenario of :mod:`uimm_jax.studies.float32` (the sweep kernel's
truth too, in scaled units: time only).  Compilation is the first chunk minus a steady
chunk.  Each sweep configuration is timed over as many chunks as fit its share of
``--budget`` seconds (all of them if they fit); the table says how many steps were timed.
``--dry-run`` shrinks every size (one batch of 16 runs of 400 samples, a 1000-sample run,
each dtype) to check every code path of the script on a CPU (about 30 s on the 2-core
development VM, compilation nearly all of it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from _common import paper_sim1

ROOT = Path(__file__).resolve().parents[1]


def _scenario(num_steps: int):
    return paper_sim1(num_steps, "gpu_throughput")


def _peak_gib() -> float | None:
    import jax

    stats = [d.memory_stats() or {} for d in jax.local_devices()]
    peaks = [s.get("peak_bytes_in_use") for s in stats]
    return max(peaks) / 2**30 if peaks and None not in peaks else None


def sweep_config(runs: int, steps: int, chunk: int, dtype: str, budget: float) -> dict:
    """Time the sweep kernel on one batch of ``runs`` runs (see the module doc)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from uimm_jax.engine.truth import run_keys
    from uimm_jax.studies import float32, run, sweep

    sc = _scenario(steps)
    f32 = dtype == "float32"
    with jax.enable_x64(not f32):
        setup = float32.setup_float32(sc)[0] if f32 else run.setup_scenario(sc, "uimm")
        devs = jax.local_devices()
        B = math.ceil(runs / (sweep.LANES * len(devs))) * sweep.LANES * len(devs)
        onset = np.tile(np.array([round(0.3 * steps), round(0.6 * steps), -1]), (B, 1))
        noise_keys, _ = run_keys(sc.seed, B)
        mesh = None
        if len(devs) > 1:
            from jax.sharding import Mesh

            mesh = Mesh(np.array(devs), ("runs",))
        jdt = jnp.float32 if f32 else jnp.float64

        def once(n):
            plan, keys, carry = sweep.batch_inputs(
                setup, onset, np.ones(onset.shape), np.ones(B), noise_keys, 3, jdt
            )
            jax.block_until_ready((plan, keys, carry))
            t0 = time.perf_counter()
            m = sweep.run_batch(setup, plan, keys, carry, n, chunk, mesh=mesh)
            return time.perf_counter() - t0, m

        t_first, _ = once(chunk)  # compilation + one chunk
        t_one, _ = once(chunk)
        n = min(steps, max(chunk, int(budget / max(t_one, 1e-9)) * chunk))
        t_run, m = once(n) if n > chunk else (t_one, None)
    return {
        "kind": "sweep",
        "dtype": dtype,
        "runs": B,
        "samples": steps,
        "timed_steps": n,
        "chunk": chunk,
        "compile_s": max(t_first - t_one, 0.0),
        "run_steps_per_s": B * n / t_run,
        "projected_s": t_run * steps / n,
        "peak_device_gib": _peak_gib(),
    }


def single_run(steps: int, dtype: str) -> dict:
    """One run of ``steps`` samples of simulation 1 by the single-run path."""
    from uimm_jax.scenario.parse import load_scenario
    from uimm_jax.studies import float32, run

    sc = load_scenario(ROOT / "scenarios" / "paper_sim1_tuned.toml")
    if sc.num_steps != steps:
        sc = _scenario(steps)
    go = float32.run_scenario_float32 if dtype == "float32" else run.run_scenario
    t0 = time.perf_counter()
    res = go(sc)
    wall = time.perf_counter() - t0
    return {
        "kind": "single run",
        "dtype": dtype,
        "runs": 1,
        "samples": steps,
        "timed_steps": steps,
        "wall_s": wall,
        "run_steps_per_s": steps / wall,
        "declarations": [d["fault"] for d in res.summary["declarations"]],
        "peak_device_gib": _peak_gib(),
    }


def _fmt(v, spec):
    return "-" if v is None else format(v, spec)


def table(rows: list[dict]) -> str:
    """The Markdown table of the measurements."""
    out = [
        "| what | dtype | runs | samples | timed steps | compile (s) | run-steps/s | "
        "full run (s) | peak device memory (GiB) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        full = r.get("projected_s", r.get("wall_s"))
        out.append(
            f"| {r['kind']} | {r['dtype']} | {r['runs']} | {r['samples']:.0e} | "
            f"{r['timed_steps']} | {_fmt(r.get('compile_s'), '.1f')} | "
            f"{r['run_steps_per_s']:.3g} | {_fmt(full, '.1f')} | "
            f"{_fmt(r.get('peak_device_gib'), '.2f')} |"
        )
    return "\n".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--dry-run", action="store_true", help="tiny sizes (a CPU check)")
    p.add_argument("--budget", type=float, default=150.0, help="seconds of sweep timing, all")
    p.add_argument("--json", type=Path, help="also write the rows here")
    args = p.parse_args(argv)
    from uimm_jax.xla_flags import apply_recommended_xla_flags

    apply_recommended_xla_flags()  # a no-op unless JAX runs on the CPU
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.dry_run:
        sizes, steps, chunk, single = (16,), 400, 100, 1000
    else:
        sizes, steps, chunk, single = (1_000, 10_000, 100_000), 100_000, 1000, 1_000_000
    print(
        f"jax {jax.__version__}, backend {jax.default_backend()}, "
        f"{len(jax.local_devices())} local device(s): {jax.local_devices()[0].device_kind}",
        flush=True,
    )
    rows = []
    share = args.budget / (2 * len(sizes))
    for dtype in ("float64", "float32"):
        for runs in sizes:
            rows.append(sweep_config(runs, steps, chunk, dtype, share))
            print(f"  {table(rows[-1:]).splitlines()[-1]}", file=sys.stderr, flush=True)
        rows.append(single_run(single, dtype))
        print(f"  {table(rows[-1:]).splitlines()[-1]}", file=sys.stderr, flush=True)
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
