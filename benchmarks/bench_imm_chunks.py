"""``imm_filter``'s scan run in chunks: does it cut the cost of its per-step outputs?

Session 8 measured that ``imm_filter``'s scan with only the log mode probabilities and the
mean is at the reference's speed, and that its other outputs cost the rest, part of it
page faults on fresh output buffers (``bench_imm_outputs.py``).  The route timed here
runs the same scan in chunks of about ``--chunk`` steps (one jitted chunk function that
carries the filter state and slices its inputs with a traced start; the inputs padded to
whole chunks with missing measurements), so each chunk's outputs are small buffers the
allocator can reuse from chunk to chunk, and copies each chunk's outputs (``np.asarray``
of a CPU array is a view) into NumPy result arrays.  On the truth of
``bench_vs_reference.py`` (``paper_sim1_tuned``, one run), interleaved, process CPU time
with its system part apart, median:

* ``reference``: ``../shared/perf/reference_step.py`` in a ``lax.scan``;
* ``imm_filter``: the public call (one scan);
* ``imm_filter's scan``: its compiled scan alone, on prepared arguments;
* ``chunks, compute only``: the chunk function over every chunk, outputs dropped;
* ``chunks + copy into reused results``: the same, each chunk copied into result arrays
  made once before the timing (faulted in): the route's bound, what it costs if result
  memory cost nothing;
* ``chunked imm_filter``: the whole route as a public call would run it: checks, padded
  inputs, fresh 64-byte aligned result arrays (``np.empty``), copies, results handed
  to JAX without a copy;
* ``... cov as 6 entries``: the chunk keeps the combined covariance's lower triangle
  (it is symmetric by construction, checked) and the copy expands it with ``np.take``;
* ``... results in 4 KB pages``: the result arrays in a fresh anonymous ``mmap`` instead
  of ``np.empty`` (which asks for transparent huge pages on arrays of 4 MB and more).

``--memory MB`` times instead what writing MB of fresh memory costs by where it comes from
(``np.empty``, with NumPy's huge pages on and off, a fresh ``mmap``, XLA, a reused array).

Every chunked output is checked bit for bit against ``imm_filter``'s, also with missing
measurements (rows and single channels).

    python benchmarks/bench_imm_chunks.py                  # 1e6 steps, 5 repeats; ~4 min
    python benchmarks/bench_imm_chunks.py --chunk 4096 --repeat 7
    python benchmarks/bench_imm_chunks.py --memory 200 --repeat 9
"""

from __future__ import annotations

import argparse
import functools
import mmap
import resource
import time
from pathlib import Path

import jax  # noqa: E402  (after uimm_jax, which sets XLA_FLAGS)
import numpy as np

import uimm_jax  # applies the XLA CPU flags before JAX starts
from bench_imm_outputs import actuator_problem
from bench_vs_reference import REPO, _load_reference, _reference_scan

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

from uimm_jax.engine.imm import imm_step  # noqa: E402
from uimm_jax.engine.scan import as_batch_of_one, drop_batch_of_one  # noqa: E402
from uimm_jax.studies.imm_filter import _check_outputs, _imm_scan, _prepare  # noqa: E402

_ALIGN = 64
_FIELDS = ("mode_probs", "log_mode_probs", "mean", "cov", "model_loglik", "loglik_increments")


def _aligned_empty(shape, dtype, small_pages: bool = False) -> np.ndarray:
    """A 64-byte aligned ``np.empty`` (JAX on a CPU then uses it without a copy).

    ``small_pages``: in a fresh anonymous ``mmap`` (4 KB pages) instead: NumPy asks for
    transparent huge pages on arrays of 4 MB and more (``madvise``).
    """
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    if small_pages:
        raw = np.frombuffer(mmap.mmap(-1, nbytes + _ALIGN), np.uint8)
    else:
        raw = np.empty(nbytes + _ALIGN, np.uint8)
    start = -raw.ctypes.data % _ALIGN
    return raw[start : start + nbytes].view(dtype).reshape(shape)


@functools.partial(jax.jit, static_argnames=("dyn", "gate", "length", "tri"))
def _chunk(dyn, cache, params, state, inputs, measurements, start, gate, length, tri):
    """``length`` steps of imm_filter's scan from row ``start``: (state, outputs)."""
    u = jax.lax.dynamic_slice_in_dim(inputs, start, length)
    y = jax.lax.dynamic_slice_in_dim(measurements, start, length)
    state, u, y = as_batch_of_one((state, u, y))
    il, jl = np.tril_indices(state.mean.shape[0])

    def body(st, uy):
        new, info = imm_step(dyn, st, cache, params, uy[0], uy[1], gate=gate)
        cov = info.cov[il, jl] if tri else info.cov
        out = (info.log_mode_probs, info.mean, cov, info.model_loglik, info.loglik_increment)
        return new, out + (info.health,)

    new, out = jax.lax.scan(body, state, (u, y))
    out = drop_batch_of_one(out)
    return drop_batch_of_one(new), (jnp.exp(out[0]),) + out


class _Chunked:
    """The chunked route for one problem: ``run(results)``; ``results=None``: fresh ones."""

    def __init__(self, bank, kw, u, y, chunk: int, tri: bool, small_pages: bool = False):
        self.args = (bank, kw, u, y)
        self.tri, self.small_pages = tri, small_pages
        N = y.shape[0]
        count = -(-N // chunk)
        self.N, self.count, self.L = N, count, -(-N // count)  # pads fewer than count rows

    def prepare(self):
        bank, kw, u, y = self.args
        keys = ("transition", "initial_mode_probs", "initial_mean", "initial_cov")
        prep = _prepare(bank, *(kw[k] for k in keys), u, y, kw["gate"])
        rows = self.count * self.L

        def pad(a, fill):
            out = _aligned_empty((rows,) + a.shape[1:], np.float64)
            out[: a.shape[0]] = a
            out[a.shape[0] :] = fill
            return jax.device_put(out)

        return prep, pad(u, 0.0), pad(y, np.nan)  # padded rows: missing measurements

    def results(self, M: int, n: int) -> list:
        N = self.N
        shapes = ((N, M), (N, M), (N, n), (N, n, n), (N, M), (N,))
        shapes = [(s, np.float64) for s in shapes] + [((N,), np.int32)]
        return [_aligned_empty(s, d, self.small_pages) for s, d in shapes]

    def run(self, results=None, copy=True):
        prep, us, ys = self.prepare()
        M, n = prep.state0.log_mode_probs.shape[0], prep.state0.mean.shape[0]
        if results is None and copy:
            results = self.results(M, n)
        il, jl = np.tril_indices(n)
        pos = np.zeros((n, n), int)
        pos[il, jl] = pos[jl, il] = np.arange(il.size)
        pos = pos.ravel()

        def put(outs, s):
            e = min(s + self.L, self.N)
            for i, (r, o) in enumerate(zip(results, outs, strict=True)):
                o = np.asarray(o)[: e - s]
                if i == 3 and self.tri:
                    np.take(o, pos, axis=1, out=r[s:e].reshape(e - s, n * n))
                else:
                    r[s:e] = o

        state, pending = prep.state0, None
        for c in range(self.count):
            state, outs = _chunk(
                prep.dyn, prep.cache, prep.params, state, us, ys, c * self.L, prep.gate,
                self.L, self.tri,
            )  # fmt: skip
            if copy and pending is not None:
                put(*pending)  # while the next chunk runs
            pending = (outs, c * self.L)
        if not copy:
            return jax.block_until_ready(state)
        put(*pending)
        return tuple(jax.device_put(r) for r in results)


def _memory(megabytes: int, repeat: int) -> None:
    """System time and faults of writing ``megabytes`` of fresh memory, by allocator."""
    from numpy._core.multiarray import _set_madvise_hugepage  # NumPy's own switch

    size = megabytes * 2**20 // 8
    src = np.ones(size)
    kept = np.zeros(size)

    def numpy_empty(hugepages=True):
        previous = _set_madvise_hugepage(hugepages)
        try:
            a = np.empty(size)
        finally:
            _set_madvise_hugepage(previous)
        np.copyto(a, src)
        return a

    def fresh_mmap():
        a = np.frombuffer(mmap.mmap(-1, size * 8), np.float64)
        np.copyto(a, src)
        return a

    variants = {
        "np.empty (NumPy asks for huge pages)": numpy_empty,
        "np.empty, NumPy's huge pages off": functools.partial(numpy_empty, False),
        "a fresh anonymous mmap (4 KB pages)": fresh_mmap,
        "XLA: jnp.zeros(...) + 1": lambda: jnp.zeros(size) + 1.0,
        "an array reused (faulted in before)": lambda: np.copyto(kept, src),
    }
    rows = {k: [] for k in variants}
    for _ in range(repeat):
        for k, f in variants.items():
            rows[k].append(_timed(f)[:3])
    thp = Path("/sys/kernel/mm/transparent_hugepage/enabled")
    mode = thp.read_text().strip() if thp.exists() else "unknown"
    print(f"\n{megabytes} MB written, {repeat} repeats, transparent huge pages: {mode}")
    print("| memory | ms | of it system ms | page faults |")
    print("|---|---:|---:|---:|")
    for k, r in rows.items():
        t, st, pf = np.median(np.asarray(r), axis=0)
        print(f"| {k} | {1e3 * t:.1f} | {1e3 * st:.1f} | {pf:.0f} |")


def _timed(fn):
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t = time.process_time()
    out = jax.block_until_ready(fn())
    dt = time.process_time() - t
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return dt, r1.ru_stime - r0.ru_stime, r1.ru_minflt - r0.ru_minflt, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=1_000_000)
    ap.add_argument("--chunk", type=int, default=16384, help="steps per chunk (about)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--reference", type=Path, default=REPO.parent / "shared" / "perf")
    ap.add_argument("--memory", type=int, default=0, metavar="MB", help="see the docstring")
    args = ap.parse_args(argv)
    if args.memory:
        return _memory(args.memory, args.repeat)
    ref = _load_reference(args.reference)
    u, y, bank, kw = actuator_problem(args.steps)
    uf, yf = u[:, None], y[:, :, 0]
    full = _Chunked(bank, kw, uf, yf, args.chunk, False)
    tri = _Chunked(bank, kw, uf, yf, args.chunk, True)
    small = _Chunked(bank, kw, uf, yf, args.chunk, False, small_pages=True)
    prep = full.prepare()[0]
    reused = full.results(4, 3)
    for r in reused:
        r[...] = 0  # faulted in before the timing
    ref_scan, ref_args = _reference_scan(ref), (ref.init(1), jnp.asarray(u), jnp.asarray(y))
    variants = {
        "reference": lambda: ref_scan(*ref_args),
        "imm_filter": lambda: uimm_jax.imm_filter(bank, inputs=uf, measurements=yf, **kw),
        "imm_filter's scan": lambda: _imm_scan(*prep, _check_outputs(None, False, True)),
        "chunks, compute only": lambda: full.run(copy=False),
        "chunks + copy into reused results": lambda: full.run(reused),
        "chunked imm_filter": full.run,
        "chunked imm_filter, cov as 6 entries": tri.run,
        "chunked imm_filter, results in 4 KB pages": small.run,
    }
    outs = {k: _timed(f)[3] for k, f in variants.items()}  # compile
    c = np.asarray(outs["imm_filter"].cov)
    print("imm_filter's cov exactly symmetric:", np.array_equal(c, np.swapaxes(c, 1, 2)))
    for k in [k for k in variants if k.startswith("chunked")]:
        same = [
            np.array_equal(np.asarray(getattr(outs["imm_filter"], f)), np.asarray(o))
            for f, o in zip(_FIELDS + ("health",), outs[k], strict=True)
        ]
        print(f"{k}: every output bit for bit imm_filter's: {all(same)}")
    del outs
    # the same with missing rows and channels (the gate is the scenario's)
    ym = yf.copy()
    ym[::97] = np.nan
    ym[5::89, 1] = np.nan
    want = uimm_jax.imm_filter(bank, inputs=uf, measurements=ym, **kw)
    got = _Chunked(bank, kw, uf, ym, args.chunk, True).run()
    same = [
        np.array_equal(np.asarray(getattr(want, f)), np.asarray(o))
        for f, o in zip(_FIELDS + ("health",), got, strict=True)
    ]
    print(f"with missing measurements, cov as 6 entries: bit for bit: {all(same)}")
    del want, got
    rows = {k: [] for k in variants}
    for _ in range(args.repeat):
        for k, f in variants.items():
            rows[k].append(_timed(f)[:3])
    N = args.steps
    base = np.median([r[0] for r in rows["reference"]])
    load = Path("/proc/loadavg").read_text()[:14]
    print(f"\n{N} steps, chunks of {full.L}, {args.repeat} repeats, load average {load}")
    print(
        "| variant | us per step | ratio to the reference | of it system us "
        "| faults per step (bytes) |"
    )
    print("|---|---:|---:|---:|---:|")
    for k, r in rows.items():
        t, st, pf = np.median(np.asarray(r), axis=0)
        us, sys_us, pf_bytes = 1e6 * t / N, 1e6 * st / N, 4096 * pf / N
        print(f"| {k} | {us:.3f} | {t / base:.2f} | {sys_us:.3f} | {pf_bytes:.0f} |")


if __name__ == "__main__":
    main()
