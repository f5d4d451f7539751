"""Time and peak memory of one tuning gradient through a long run, against the forward pass.

For each batch size, two fresh subprocesses run the same loss
(:func:`uimm_jax.studies.tune.loss_and_parts`: truth simulated inside the loop, exact hard UIMM,
decision surrogate, nested ``lax.scan`` with ``jax.checkpoint`` on segments of
``segment`` samples, ``sqrt(N) / 4`` by default):

* ``forward``: ``jax.jit(loss)`` alone (its peak memory);
* ``gradient``: ``jax.jit(jax.value_and_grad(loss))`` with respect to every tunable
  parameter (transition logits, threshold, persistence, noise scales), and the forward
  pass again, timed in turns with the gradient in the same process.

Each is compiled ahead of time (``lower().compile()``, timed separately) and then executed
``--repeat`` times; the steady time is the minimum.  The ratio is of process CPU time
(``time.process_time``) measured in turns in the gradient's process, so that other jobs on
a shared machine slow both alike; wall times are printed beside it.  Peak memory is the
subprocess's peak resident set size (``ru_maxrss``: compilation included, so an upper
bound) and XLA's own estimate of the executable's buffers (``memory_analysis``: arguments
+ outputs + temporaries).  ``--precomputed`` stores the truth first
(:func:`uimm_jax.studies.tune.precompute_truth`, as the tuning examples do) so both passes
run the diagnoser and the surrogate only.

    python benchmarks/bench_gradient.py                    # 1e6 samples, batch 1 and 8
    python benchmarks/bench_gradient.py --batch 1 --repeat 3
    python benchmarks/bench_gradient.py --batch 1 --precomputed
    python benchmarks/bench_gradient.py --check 2000       # checkpointed == plain gradient

Targets: gradient <= 3x the forward time (issue 12; issue 4 asked <= 5x), <= 2 GB peak at
batch 1.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "scenarios" / "paper_sim1.toml"


def _setup():
    from uimm_jax.xla_flags import apply_recommended_xla_flags

    apply_recommended_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)
    return jax


def _problem(steps: int, batch: int, segment: int | None, checkpoint: bool = True):
    import warnings

    from uimm_jax.scenario.parse import load_scenario
    from uimm_jax.studies import tune

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sc = load_scenario(SCENARIO)
    dur = steps * float(sc.dt)
    sc = tune.rescale_scenario(sc, dur)
    config = tune.TuneConfig(tune_noise=True, segment=segment, checkpoint=checkpoint)
    problem, data = tune.make_batch(sc, [tune.scenario_case(sc)], batch, seed=7)
    raw = tune.init_params(
        sc.transition_matrix(), sc.filter.decision.threshold, sc.filter.decision.hold, config
    )
    return tune, problem, data, raw, config


def _timed(compiled, args, times: dict, name: str):
    """Run once; append ``(cpu_s, wall_s)`` to ``times[name]``."""
    import jax

    t0, c0 = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(compiled(*args))
    times.setdefault(name, []).append((time.process_time() - c0, time.perf_counter() - t0))
    return out


def _xla_bytes(compiled):
    mem = compiled.memory_analysis()
    if mem is None:
        return None
    return int(
        mem.argument_size_in_bytes
        + mem.output_size_in_bytes
        + mem.temp_size_in_bytes
        - mem.alias_size_in_bytes
    )


def _worker(args) -> dict:
    jax = _setup()
    import resource

    import numpy as np

    from uimm_jax.studies import tune_loss

    tune, problem, data, raw, config = _problem(args.steps, args.batch, args.segment)
    if args.precomputed:
        data = tune.precompute_truth(problem, data)

    def loss(r, b):
        return tune.loss_and_parts(r, problem, b, config)

    compiled, compile_s = {}, {}
    names = ("forward",) if args.mode == "forward" else ("forward", "gradient")
    for name in names[::-1]:  # the gradient first: its compilation dominates the peak
        fn = jax.jit(loss) if name == "forward" else jax.jit(jax.value_and_grad(loss, has_aux=True))
        t0 = time.perf_counter()
        compiled[name] = fn.lower(raw, data).compile()
        compile_s[name] = time.perf_counter() - t0
    times: dict = {}
    outs = {}
    for _ in range(args.repeat):  # in turns
        for name in names:
            outs[name] = _timed(compiled[name], (raw, data), times, name)
    grads = None
    if "gradient" in outs:
        grads = {
            k: np.asarray(v).tolist()
            for k, v in outs["gradient"][1]._asdict().items()
            if np.asarray(v).size
        }
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {
        "mode": args.mode,
        "steps": args.steps,
        "batch": args.batch,
        "precomputed": bool(args.precomputed),
        "segment": tune_loss._segment_length(args.steps, config),
        "compile_s": compile_s,
        "cpu_s": {k: min(c for c, _ in v) for k, v in times.items()},
        "wall_s": {k: min(w for _, w in v) for k, v in times.items()},
        "times": times,
        "peak_rss_bytes": rss,
        "xla_buffer_bytes": {k: _xla_bytes(c) for k, c in compiled.items()},
        "loss": float(outs["forward"][0]),
        "grads": grads,
    }


def _check(steps: int) -> None:
    """Checkpointed nested-scan gradient equals the plain reverse-mode gradient."""
    jax = _setup()
    import numpy as np

    tune, problem, data, raw, config = _problem(steps, 2, None, True)
    _, vg = tune.make_loss_fn(problem, config)
    _, vg_plain = tune.make_loss_fn(
        problem, tune.TuneConfig(tune_noise=True, segment=steps, checkpoint=False)
    )
    (l1, _), g1 = vg(raw, data)
    (l2, _), g2 = vg_plain(raw, data)
    print(f"loss checkpointed {float(l1):.15g} plain {float(l2):.15g}")
    worst = 0.0
    for name, a, b in zip(raw._fields, g1, g2, strict=True):
        a, b = np.asarray(a), np.asarray(b)
        err = float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))
        worst = max(worst, err)
        print(f"  {name:18s} max rel diff {err:.2e}")
    del jax
    print("OK" if worst < 1e-9 else "MISMATCH")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=1_000_000)
    p.add_argument("--batch", type=int, nargs="+", default=[1, 8])
    p.add_argument("--segment", type=int, default=None, help="checkpoint segment (sqrt(N) / 4)")
    p.add_argument("--precomputed", action="store_true", help="store the truth first")
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--json", help="write the results here")
    p.add_argument("--check", type=int, metavar="N", help="only compare gradients at N steps")
    p.add_argument("--mode", choices=("forward", "gradient"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.check:
        _check(args.check)
        return 0
    if args.mode:  # worker
        args.batch = args.batch[0]
        print("RESULT " + json.dumps(_worker(args)), flush=True)
        return 0
    rows = []
    for b in args.batch:
        for mode in ("forward", "gradient"):
            cmd = [sys.executable, __file__, "--mode", mode, "--steps", str(args.steps)]
            cmd += ["--batch", str(b), "--repeat", str(args.repeat)]
            if args.segment:
                cmd += ["--segment", str(args.segment)]
            if args.precomputed:
                cmd += ["--precomputed"]
            print(f"running {mode} batch {b} ...", file=sys.stderr, flush=True)
            proc = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
            line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
            if proc.returncode or not line:
                print(proc.stdout[-2000:], proc.stderr[-4000:], file=sys.stderr)
                return 1
            rows.append(json.loads(line[0][7:]))
    import jax

    truth = "precomputed truth" if args.precomputed else "truth in the loop"
    print(
        f"# bench_gradient: {args.steps} samples of paper_sim1 ({truth}), jax {jax.__version__}, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, float64, "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    print(
        "| batch | segment | forward us / run-step | gradient us / run-step | x forward "
        "| wall: forward / gradient (s) | compile: forward / gradient (s) "
        "| peak RSS: forward / gradient (MB) | XLA buffers: forward / gradient (MB) |"
    )
    print("|---:|---:|---:|---:|---:|---|---|---|---|")
    fwd = {r["batch"]: r for r in rows if r["mode"] == "forward"}
    for r in rows:
        if r["mode"] != "gradient":
            continue
        f = fwd[r["batch"]]
        per = r["steps"] * r["batch"]
        cf, cg = r["cpu_s"]["forward"], r["cpu_s"]["gradient"]
        xf, xg = f["xla_buffer_bytes"]["forward"], r["xla_buffer_bytes"]["gradient"]
        mb = lambda v: "" if v is None else f"{v / 2**20:.1f}"  # noqa: E731
        print(
            f"| {r['batch']} | {r['segment']} | {cf / per * 1e6:.2f} | {cg / per * 1e6:.2f} "
            f"| **{cg / cf:.2f}** | {r['wall_s']['forward']:.2f} / {r['wall_s']['gradient']:.2f} "
            f"| {f['compile_s']['forward']:.1f} / {r['compile_s']['gradient']:.1f} "
            f"| {f['peak_rss_bytes'] / 2**20:.0f} / {r['peak_rss_bytes'] / 2**20:.0f} "
            f"| {mb(xf)} / {mb(xg)} |"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
