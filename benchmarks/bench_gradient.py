"""Time and peak memory of one tuning gradient through a long run, against the forward pass.

For each batch size, two fresh subprocesses run the same loss
(:func:`uimm_jax.studies.tune.loss_and_parts`: truth simulated inside the loop, exact hard UIMM,
decision surrogate, nested ``lax.scan`` with ``jax.checkpoint`` on segments of
``sqrt(N)`` samples):

* ``forward``: ``jax.jit(loss)``;
* ``gradient``: ``jax.jit(jax.value_and_grad(loss))`` with respect to every tunable
  parameter (transition logits, threshold, persistence, noise scales).

Each is compiled ahead of time (``lower().compile()``, timed separately) and then executed
``--repeat`` times; the steady time is the minimum.  Peak memory is the subprocess's peak
resident set size (``ru_maxrss``: compilation included, so an upper bound) and XLA's own
estimate of the executable's buffers (``memory_analysis``: arguments + outputs + temporaries).

    python benchmarks/bench_gradient.py                    # 1e6 samples, batch 1 and 8
    python benchmarks/bench_gradient.py --steps 100000 --batch 1
    python benchmarks/bench_gradient.py --check 2000       # checkpointed == plain gradient

Targets (issue 4): gradient <= 5x the forward time, <= 2 GB peak at batch 1.
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


def _worker(args) -> dict:
    jax = _setup()
    import resource

    from uimm_jax.studies import tune_loss

    tune, problem, data, raw, config = _problem(args.steps, args.batch, args.segment)

    def loss(r, b):
        return tune.loss_and_parts(r, problem, b, config)

    fn = (
        jax.jit(loss) if args.mode == "forward" else jax.jit(jax.value_and_grad(loss, has_aux=True))
    )
    t0 = time.perf_counter()
    compiled = fn.lower(raw, data).compile()
    compile_s = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    xla_bytes = None
    if mem is not None:
        xla_bytes = int(
            mem.argument_size_in_bytes
            + mem.output_size_in_bytes
            + mem.temp_size_in_bytes
            - mem.alias_size_in_bytes
        )
    times = []
    out = None
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(raw, data))
        times.append(time.perf_counter() - t0)
    loss_value = float(out[0][0] if args.mode == "gradient" else out[0])
    grads = None
    if args.mode == "gradient":
        import numpy as np

        grads = {
            k: np.asarray(v).tolist() for k, v in out[1]._asdict().items() if np.asarray(v).size
        }
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {
        "mode": args.mode,
        "steps": args.steps,
        "batch": args.batch,
        "segment": tune_loss._segment_length(args.steps, config),
        "compile_s": compile_s,
        "time_s": min(times),
        "times_s": times,
        "peak_rss_bytes": rss,
        "xla_buffer_bytes": xla_bytes,
        "loss": loss_value,
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
    p.add_argument("--segment", type=int, default=None, help="checkpoint segment (sqrt N)")
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
            print(f"running {mode} batch {b} ...", file=sys.stderr, flush=True)
            proc = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
            line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
            if proc.returncode or not line:
                print(proc.stdout[-2000:], proc.stderr[-4000:], file=sys.stderr)
                return 1
            rows.append(json.loads(line[0][7:]))
    import jax

    print(
        f"# bench_gradient: {args.steps} samples of paper_sim1, jax {jax.__version__}, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, float64"
    )
    print(
        "| batch | pass | compile (s) | time (s) | us / run-step | x forward "
        "| peak RSS (MB) | XLA buffers (MB) |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|")
    fwd = {}
    for r in rows:
        if r["mode"] == "forward":
            fwd[r["batch"]] = r["time_s"]
        ratio = r["time_s"] / fwd[r["batch"]]
        xla = "" if r["xla_buffer_bytes"] is None else f"{r['xla_buffer_bytes'] / 2**20:.1f}"
        print(
            f"| {r['batch']} | {r['mode']} | {r['compile_s']:.1f} | {r['time_s']:.2f} "
            f"| {r['time_s'] / (r['steps'] * r['batch']) * 1e6:.2f} | {ratio:.2f} "
            f"| {r['peak_rss_bytes'] / 2**20:.0f} | {xla} |"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
