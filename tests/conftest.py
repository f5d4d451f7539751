"""Test-session setup: the recommended XLA CPU flags (before JAX starts), float64, and a
persistent compilation cache private to the session.

The library never changes JAX's configuration; the test session does, as the CLI does:
float64 is the reference precision.  float32 tests use ``jax.enable_x64(False)`` locally.

Compilation cache: most of the suite's time is XLA compiling.  Many tests compile the same
program through different ``jax.jit`` objects (closures built per call, ``jax.clear_caches``,
the CLI's subprocesses), which JAX's in-memory caches cannot share; JAX's persistent cache
(keyed on the HLO, the compile options, the XLA flags and the devices) can.  The session
uses a fresh temporary directory, removed at exit, so nothing carries over between runs;
the environment variables reach the subprocesses the tests start.  A cache hit loads the
executable XLA compiled for the same key, so results do not change.  Measured in
README.md ("Quick start", after the test command).  ``UIMM_JAX_TEST_NO_CACHE=1`` turns it off.
Under ``pytest -n 2`` (the README's command) each worker process has its own cache: one
cache shared by the two workers was measured no faster (4 min 39 s against 4 min 41 s).
"""

import atexit
import gc
import os
import shutil
import tempfile

# Read by JAX when it is imported, in the tests' subprocesses too; set before uimm_jax
# imports JAX (and again through jax.config below, should something have imported it first).
_CACHE = {}
if os.environ.get("UIMM_JAX_TEST_NO_CACHE", "") in ("", "0"):
    _cache_dir = tempfile.mkdtemp(prefix="uimm_jax_test_xla_cache_")
    atexit.register(shutil.rmtree, _cache_dir, ignore_errors=True)
    _CACHE = {
        "jax_compilation_cache_dir": _cache_dir,
        "jax_persistent_cache_min_compile_time_secs": 0.0,  # the default skips < 1 s
        "jax_persistent_cache_min_entry_size_bytes": -1,  # no size limit
    }
    for _name, _value in _CACHE.items():
        os.environ[_name.upper()] = str(_value)

# Python's cyclic garbage collector: the suite keeps about a million objects alive (JAX's
# traced and compiled functions), which every full collection walks.  Fewer, later
# collections: cyclic garbage lives a little longer (memory only; no result changes).
# Measured on tests/engine (session 14, one process each, gc.callbacks): 17 full
# collections and 7.6 s of collection against 3 and 2.1 s.
gc.set_threshold(50_000, 20, 1000)

from uimm_jax.xla_flags import apply_recommended_xla_flags  # noqa: E402

apply_recommended_xla_flags()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
for _name, _value in _CACHE.items():
    jax.config.update(_name, _value)
