"""Monte Carlo throughput and memory: run-steps/s against batch size, UIMM (M = 4), float64.

Every configuration runs in its own subprocess (fresh XLA, its own peak memory VmHWM from
/proc/self/status; XLA's buffers are not seen by tracemalloc):

* ``single``: the engine's single-run path (``run.simulate_scenario`` then
  ``run.filter_measurements``, two scans, per-step outputs kept) -- the baseline;
* ``fused B``: the Monte Carlo kernel of :mod:`uimm_jax.studies.sweep`
  (:func:`uimm_jax.engine.scan.simulate_diagnose`: truth + UIMM + metrics per chunk, nothing
  per step stored) on a batch of B runs of the paper's simulation 1
  (valve wear at 30 % of the run, leakage at 60 %), on 1 device, and on 2 forced host
  devices (``--xla_force_host_platform_device_count=2``, the run axis sharded);
* ``reference``: ``../shared/perf/reference_step.py`` (the filter step only, no truth) on a
  batch of 64 runs of the same truth, 1 device: the engine issue's measuring stick; the
  table gives every row's time per run-step against it (truth counted in the fused rows);
* ``memory``: a fixed batch over 1e4 and 1e6 samples (same compiled chunk of 1e4 steps):
  the peak must not grow with the number of samples;
* ``--anatomy``: instead of the table, the fused chunk and its parts at ``--ref-batch``
  runs on one device, interleaved in one process, in CPU seconds per run-step: the truth
  (its noise draw alone, then the whole truth scan), the diagnoser with the metrics, the
  fused chunk (with XLA's defaults, then as the sweep compiles it), and the reference step
  on the same truth.
* ``--options``: instead of the table, the sweep's chunk on 2 forced host devices at
  ``--options-batch`` runs, compiled with XLA's defaults and with the sweep's
  ``CHUNK_COMPILER_OPTIONS``, at each of ``--options-chunks`` chunk lengths, interleaved
  in one process: CPU µs per run-step (all threads) and whether every metric is the same.

Compilation is timed apart (first chunk minus a steady chunk).  Each row also gives the
process's CPU time per run-step, summed over its threads: on a shared machine the wall-time
throughput of the two-device rows falls with the load, while two free cores would give at
most ``2 / (CPU µs per run-step)`` M run-steps/s.  Ratios are against the
single-run baseline measured in the same invocation.  Defaults finish in < 10 minutes on a
quiet 2-core machine::

    python benchmarks/bench_montecarlo.py               # full table
    python benchmarks/bench_montecarlo.py --quick       # a smoke run (~2 min)
    python benchmarks/bench_montecarlo.py --anatomy     # where a run-step's time goes
    python benchmarks/bench_montecarlo.py --options     # the sweep's compile options
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from _common import paper_sim1, vm_mib

ROOT = Path(__file__).resolve().parents[1]


def _scenario(num_steps: int):
    return paper_sim1(num_steps, "bench")


def worker(args) -> dict:
    """Run one configuration in this (fresh) process and return its measurements."""
    from uimm_jax.xla_flags import apply_recommended_xla_flags

    apply_recommended_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from uimm_jax.engine.truth import run_keys
    from uimm_jax.studies import run, sweep

    sc = _scenario(args.steps)
    N, L = args.steps, args.chunk
    rss0 = vm_mib("VmRSS")
    if args.worker == "reference":
        ref = _load_reference()
        from uimm_jax.engine.scan import truth_scan

        setup = run.setup_scenario(sc, "uimm")
        B = args.batch
        onset = np.tile(np.array([round(0.3 * N), round(0.6 * N), -1]), (B, 1))
        noise_keys, _ = run_keys(sc.seed, B)
        plan, keys, carry = sweep.batch_inputs(
            setup, onset, np.ones(onset.shape), np.ones(B), noise_keys, 3, jnp.float64
        )
        _, (us, _, ys, _) = jax.jit(
            lambda pl, k, x, ks: truth_scan(
                setup.diagnoser.dyn, float(sc.dt), 1, pl, setup.signal, k, x, ks
            )
        )(plan, keys, carry.x, jnp.arange(N, dtype=jnp.int32))
        step = ref.make_step()
        scan = jax.jit(lambda c, u, z: jax.lax.scan(step, c, (u, z)))
        c0 = ref.init(B)

        def once(n):
            t0, c0_ = time.perf_counter(), time.process_time()
            jax.block_until_ready(scan(c0, us[:n], ys[:n]))
            return time.perf_counter() - t0, time.process_time() - c0_

        t_first, _ = once(N)
        hwm_compile = vm_mib("VmHWM")
        t_run, cpu_run = min(once(N) for _ in range(3))
    elif args.worker == "single":

        def once(n):
            s = run.setup_scenario(_scenario(n) if n != N else sc, "uimm")
            t0, c0 = time.perf_counter(), time.process_time()
            tr = run.simulate_scenario(s, chunk=L)
            _, out = run.filter_measurements(s, tr["y"], tr["u"], chunk=L)
            np.asarray(out["declared"])
            return time.perf_counter() - t0, time.process_time() - c0

        t_first, _ = once(L)  # compile + one chunk
        hwm_compile = vm_mib("VmHWM")
        t_run, cpu_run = once(N)
        B = 1
    else:
        setup = run.setup_scenario(sc, "uimm")
        B = args.batch
        onset = np.tile(np.array([round(0.3 * N), round(0.6 * N), -1]), (B, 1))
        noise_keys, _ = run_keys(sc.seed, B)
        devs = jax.devices()
        mesh = None
        if len(devs) > 1:
            from jax.sharding import Mesh

            mesh = Mesh(np.array(devs), ("runs",))

        def once(n):
            plan, keys, carry = sweep.batch_inputs(
                setup, onset, np.ones(onset.shape), np.ones(B), noise_keys, 3, jnp.float64
            )
            jax.block_until_ready((plan, keys, carry))
            t0, c0 = time.perf_counter(), time.process_time()
            m = sweep.run_batch(setup, plan, keys, carry, n, L, mesh=mesh)
            return time.perf_counter() - t0, time.process_time() - c0, m

        t_first, _, _ = once(L)
        hwm_compile = vm_mib("VmHWM")
        t_run, cpu_run, m = once(N)
        if args.check:
            assert np.all(m.decl_step[:, 0] >= round(0.3 * N)), m.decl_step
    per_chunk = t_run * L / N
    return {
        "worker": args.worker,
        "batch": B,
        "devices": len(jax.devices()),
        "steps": N,
        "chunk": L,
        "run_steps_per_s": B * N / t_run,
        "run_s": t_run,
        "cpu_us_per_run_step": cpu_run / (B * N) * 1e6,
        "compile_s": max(t_first - per_chunk, 0.0),
        "rss_start_mib": rss0,
        "hwm_after_compile_mib": hwm_compile,
        "hwm_end_mib": vm_mib("VmHWM"),
    }


def _load_reference():
    import importlib.util

    src = ROOT.parent / "shared" / "perf" / "reference_step.py"
    spec = importlib.util.spec_from_file_location("reference_step", src)
    ref = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ref)
    return ref


def anatomy(B: int, L: int, repeat: int) -> list[tuple[str, float]]:
    """CPU us per run-step of the fused chunk's parts at B runs, one device, interleaved."""
    from uimm_jax.xla_flags import apply_recommended_xla_flags

    apply_recommended_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from uimm_jax.engine import scan
    from uimm_jax.engine.truth import run_keys, standard_noise
    from uimm_jax.studies import run, sweep
    from uimm_jax.studies.sweep_batch import CHUNK_COMPILER_OPTIONS

    sc = _scenario(L)
    setup = run.setup_scenario(sc, "uimm")
    diag, params, dt, sig = setup.diagnoser, setup.params, float(sc.dt), setup.signal
    onset = np.tile(np.array([round(0.3 * L), round(0.6 * L), -1]), (B, 1))
    plan, keys, carry = sweep.batch_inputs(
        setup, onset, np.ones(onset.shape), np.ones(B), run_keys(sc.seed, B)[0], 3, jnp.float64
    )
    ks = jnp.arange(L, dtype=jnp.int32)
    size = carry.x.shape[0] + plan.Gr.shape[0]
    truth = jax.jit(lambda pl, k, x, ks: scan.truth_scan(diag.dyn, dt, 1, pl, sig, k, x, ks))
    _, (us, xs, ys, codes) = truth(plan, keys, carry.x, ks)
    variants = {
        "truth: noise draw only": (
            jax.jit(
                lambda k, ks: jax.vmap(lambda s: standard_noise(k, s, size, (B,), jnp.float64))(ks)
            ),
            (keys, ks),
        ),
        "truth (draw + scan)": (truth, (plan, keys, carry.x, ks)),
        "diagnoser + metrics": (
            jax.jit(lambda c, *a: scan.diagnose_scan(diag, 1, params, c, *a)),
            (carry, ks, us, xs, ys, codes),
        ),
        "fused chunk (truth + diagnoser + metrics)": (
            jax.jit(
                lambda pl, k, c, ks: scan.simulate_diagnose(diag, dt, 1, params, pl, sig, k, c, ks)
            ),
            (plan, keys, carry, ks),
        ),
    }
    variants["fused chunk, the sweep's compile options"] = (
        jax.jit(
            variants["fused chunk (truth + diagnoser + metrics)"][0].__wrapped__,
            compiler_options=CHUNK_COMPILER_OPTIONS,
        ),
        (plan, keys, carry, ks),
    )
    if (ROOT.parent / "shared" / "perf" / "reference_step.py").exists():
        ref = _load_reference()
        step = ref.make_step()
        variants["reference step (filter only)"] = (
            jax.jit(lambda c, u, z: jax.lax.scan(step, c, (u, z))),
            (ref.init(B), us, ys),
        )
    for f, a in variants.values():
        jax.block_until_ready(f(*a))
    times = {name: [] for name in variants}
    for _ in range(repeat):
        for name, (f, a) in variants.items():
            t0 = time.process_time()
            jax.block_until_ready(f(*a))
            times[name].append(time.process_time() - t0)
    return [(name, min(t) / (L * B) * 1e6) for name, t in times.items()]


def compare_options(B: int, N: int, chunks: list[int], repeat: int) -> list[tuple]:
    """The sweep's sharded chunk with XLA's defaults and with its options (module doc)."""
    from uimm_jax.xla_flags import apply_recommended_xla_flags

    apply_recommended_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import Mesh

    from uimm_jax.engine.scan import scan_chunked
    from uimm_jax.engine.truth import run_keys
    from uimm_jax.studies import run, sweep
    from uimm_jax.studies import sweep_batch as sb

    sc = _scenario(N)
    setup = run.setup_scenario(sc, "uimm")
    mesh = Mesh(np.array(jax.devices()), ("runs",))
    onset = np.tile(np.array([round(0.3 * N), round(0.6 * N), -1]), (B, 1))
    plan, keys, carry = sweep.batch_inputs(
        setup, onset, np.ones(onset.shape), np.ones(B), run_keys(sc.seed, B)[0], 3, jnp.float64
    )
    specs = sb._specs(carry, plan, keys)
    carry, plan, keys = (
        sb._place(t, sp, mesh) for t, sp in zip((carry, plan, keys), specs, strict=True)
    )
    opts = {"XLA defaults": (), "CHUNK_COMPILER_OPTIONS": None}
    fns = {
        name: sb._sharded_chunk(setup.diagnoser, float(sc.dt), 1, mesh, *specs, o)
        for name, o in opts.items()
    }

    def drive(fn, L):
        def chunk(c, k0, ks):
            return fn(setup.params, plan, setup.signal, keys, c, ks), None

        c, _ = scan_chunked(chunk, carry, N, chunk=L, keep_outputs=False)
        return jax.block_until_ready(c.metrics)

    variants = {(name, L): fn for name, fn in fns.items() for L in chunks}
    first = None
    same = {}
    for v, fn in variants.items():
        out = jax.tree.leaves(drive(fn, v[1]))  # compiles (the last chunk may differ)
        first = first or out
        same[v] = all(np.array_equal(a, b) for a, b in zip(first, out, strict=True))
    times = {v: [] for v in variants}
    for _ in range(repeat):
        for v, fn in variants.items():
            t0 = time.process_time()
            drive(fn, v[1])
            times[v].append((time.process_time() - t0) / (B * N) * 1e6)
    return [(v[0], v[1], min(t), sorted(t)[len(t) // 2], same[v]) for v, t in times.items()]


def _spawn(mode: str, batch: int, steps: int, chunk: int, devices: int, timeout: float) -> dict:
    env = dict(os.environ)
    flags = env.get("XLA_FLAGS", "")
    if devices > 1:
        flags += f" --xla_force_host_platform_device_count={devices}"
    env["XLA_FLAGS"] = flags.strip()
    env["JAX_PLATFORMS"] = "cpu"
    cmd = [
        sys.executable,
        __file__,
        "--worker",
        mode,
        "--batch",
        str(batch),
        "--steps",
        str(steps),
        "--chunk",
        str(chunk),
    ]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _steps_for(batch: int, target: float, chunk: int) -> tuple[int, int]:
    n = max(int(target / batch), chunk)
    L = min(chunk, n)
    return max(L, round(n / L) * L), L


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--worker", choices=("single", "fused", "reference", "options"), help=argparse.SUPPRESS
    )
    p.add_argument("--batch", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--steps", type=int, default=10_000, help=argparse.SUPPRESS)
    p.add_argument("--check", action="store_true", help=argparse.SUPPRESS)
    p.add_argument(
        "--batches",
        default="1,2,4,8,16,32,64,128,256,512",
        help="comma-separated batch sizes (default 1..512)",
    )
    p.add_argument(
        "--two-device-batches",
        default="64,256,512",
        help="batch sizes also run sharded over 2 forced host devices ('' to skip)",
    )
    p.add_argument("--run-steps", type=float, default=2e6, help="run-steps timed per configuration")
    p.add_argument("--chunk", type=int, default=5000, help="steps per compiled chunk")
    p.add_argument("--mem-batch", type=int, default=32, help="batch of the memory test")
    p.add_argument("--ref-batch", type=int, default=64, help="runs of the reference row")
    p.add_argument("--mem-steps", default="10000,1000000", help="sample counts of the memory test")
    p.add_argument("--quick", action="store_true", help="a short smoke run")
    p.add_argument(
        "--anatomy",
        action="store_true",
        help="time the fused chunk's parts at --ref-batch runs instead (one device)",
    )
    p.add_argument("--repeat", type=int, default=7, help="repeats of --anatomy (default 7)")
    p.add_argument(
        "--options", action="store_true", help="compare the sweep's compile options instead"
    )
    p.add_argument("--options-batch", type=int, default=128, help="runs of --options")
    p.add_argument("--options-steps", type=int, default=30000, help="steps of --options")
    p.add_argument("--options-chunks", default="5000,15625", help="chunk lengths of --options")
    p.add_argument("--json", help="also write the rows to this JSON file")
    args = p.parse_args(argv)
    if args.options and not args.worker:
        env = dict(os.environ, JAX_PLATFORMS="cpu")
        flags = env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
        env["XLA_FLAGS"] = flags.strip()
        cmd = [sys.executable, __file__, "--worker", "options", *(argv or sys.argv[1:])]
        return subprocess.run(cmd, env=env).returncode
    if args.worker == "options":
        chunks = [int(c) for c in args.options_chunks.split(",")]
        B, N = args.options_batch, args.options_steps
        print(f"# bench_montecarlo --options: B={B} on 2 devices, {N} steps, interleaved")
        print("| compiled with | chunk | CPU µs per run-step, min | median | same metrics |")
        print("|---|---:|---:|---:|---|")
        for name, L, lo, med, same in compare_options(B, N, chunks, args.repeat):
            print(f"| {name} | {L} | {lo:.4f} | {med:.4f} | {same} |")
        return 0
    if args.worker:
        print(json.dumps(worker(args)))
        return 0
    if args.anatomy:
        B = args.ref_batch
        print(f"# bench_montecarlo --anatomy: B={B}, chunk {args.chunk}, CPU time, interleaved")
        print("| part | CPU us per run-step |")
        print("|---|---:|")
        for name, us in anatomy(B, args.chunk, args.repeat):
            print(f"| {name} | {us:.3f} |")
        return 0
    if args.quick:
        args.batches, args.two_device_batches = "1,16,128", "64,128"
        args.run_steps, args.mem_steps = 5e5, "10000,100000"
    batches = [int(b) for b in args.batches.split(",") if b]
    two = [int(b) for b in args.two_device_batches.split(",") if b]
    t_all = time.perf_counter()
    import platform

    print(
        f"# bench_montecarlo: UIMM M=4 float64, paper sim 1; {os.cpu_count()} CPUs, "
        f"python {platform.python_version()}",
        flush=True,
    )
    rows = []
    n, L = _steps_for(1, args.run_steps / 4, args.chunk)
    base = _spawn("single", 1, n, L, 1, 1800)
    base["label"] = "single run (run: simulate + filter)"
    rows.append(base)
    print(
        f"baseline single run: {base['run_steps_per_s'] / 1e6:.3f} M steps/s "
        f"(compile {base['compile_s']:.1f} s)",
        flush=True,
    )
    refs = []
    if (ROOT.parent / "shared" / "perf" / "reference_step.py").exists():
        n, L = _steps_for(args.ref_batch, args.run_steps, args.chunk)
        ref = _spawn("reference", args.ref_batch, n, n, 1, 1800)
        ref["label"] = f"reference step (shared/perf, filter only), B={args.ref_batch}, 1 device"
        refs.append(ref)
        print(f"{ref['label']}: {ref['run_steps_per_s'] / 1e6:.3f} M run-steps/s", flush=True)
    for devices, bs in ((1, batches), (2, two)):
        for b in bs:
            n, L = _steps_for(b, args.run_steps, args.chunk)
            r = _spawn("fused", b, n, L, devices, 1800)
            r["label"] = f"fused B={b}, {devices} device(s)"
            rows.append(r)
            print(
                f"{r['label']:32s} {r['run_steps_per_s'] / 1e6:7.3f} M run-steps/s "
                f"x{r['run_steps_per_s'] / base['run_steps_per_s']:6.2f}  compile "
                f"{r['compile_s']:5.1f} s  peak {r['hwm_end_mib']:7.1f} MiB",
                flush=True,
            )
    mem = []
    for steps in [int(float(s)) for s in args.mem_steps.split(",") if s]:
        r = _spawn("fused", args.mem_batch, steps, min(10_000, steps), 1, 3600)
        r["label"] = f"memory B={args.mem_batch}, {steps:.0e} samples"
        mem.append(r)
        print(
            f"{r['label']:32s} peak {r['hwm_end_mib']:7.1f} MiB (after compile "
            f"{r['hwm_after_compile_mib']:7.1f} MiB), {r['run_steps_per_s'] / 1e6:.3f} M "
            "run-steps/s",
            flush=True,
        )
    print()
    head = "| configuration | run-steps/s | vs single run | time per run-step vs reference "
    print(head + "| CPU µs per run-step (all threads) | compile (s) | peak RSS (MiB) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows + refs:
        vs_ref = f"{refs[0]['run_steps_per_s'] / r['run_steps_per_s']:.2f}x" if refs else "n/a"
        print(
            f"| {r['label']} | {r['run_steps_per_s'] / 1e6:.3f} M | "
            f"{r['run_steps_per_s'] / base['run_steps_per_s']:.2f}x | {vs_ref} | "
            f"{r['cpu_us_per_run_step']:.3f} | {r['compile_s']:.1f} | {r['hwm_end_mib']:.0f} |"
        )
    print()
    print("| memory test | samples | peak after compile (MiB) | peak at end (MiB) |")
    print("|---|---|---|---|")
    for r in mem:
        print(
            f"| fused B={r['batch']} | {r['steps']:.0e} | {r['hwm_after_compile_mib']:.0f} | "
            f"{r['hwm_end_mib']:.0f} |"
        )
    print(f"\ntotal wall time {time.perf_counter() - t_all:.0f} s")
    if args.json:
        doc = {"rows": rows, "reference": refs, "memory": mem}
        Path(args.json).write_text(json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
