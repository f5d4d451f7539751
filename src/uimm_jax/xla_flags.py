"""XLA CPU flags that make the filter's time loop fast, and how to opt out.

Two flags matter on the CPU (measured in benchmarks/README.md):

* ``--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=<large>`` lets
  XLA CPU hoist a whole ``lax.scan`` into one compiled kernel when its body has no dots
  or custom calls -- the engine's bank algebra is written that way
  (:mod:`uimm_jax.engine._wide`, :mod:`uimm_jax.engine._smallmat`).  Without it each step pays
  per-kernel dispatch (measured 4x slower for the actuator bank; 30x before the kernel
  was restructured into fewer, wider operations).
* ``--xla_cpu_experimental_ynn_fusion_type=`` (empty) turns off the YNNPACK fusions that
  XLA CPU otherwise picks for batched multiply-reduce patterns from a batch of about 64
  runs, where throughput collapses.

XLA reads ``XLA_FLAGS`` once, when JAX's backend starts, so they must be set before the
first JAX computation.  The library never sets them at import; the CLI, the benchmarks
and the tests call :func:`apply_recommended_xla_flags` first.  Opt out by setting the
environment variable ``UIMM_JAX_NO_XLA_FLAGS=1``; user code may call the function itself
(before touching JAX) or set ``XLA_FLAGS`` by hand.

This module does not import JAX.
"""

from __future__ import annotations

import os
import sys

__all__ = ["RECOMMENDED_XLA_FLAGS", "apply_recommended_xla_flags"]

RECOMMENDED_XLA_FLAGS = (
    "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000000",
    "--xla_cpu_experimental_ynn_fusion_type=",
)


def _backend_started() -> bool:
    xb = sys.modules.get("jax._src.xla_bridge")
    if xb is None:
        return False
    backends = getattr(xb, "_backends", None)
    return bool(backends)


def apply_recommended_xla_flags(*, force: bool = False) -> bool:
    """Append the recommended flags to ``XLA_FLAGS`` unless opted out or already set.

    Args:
        force: apply even if ``UIMM_JAX_NO_XLA_FLAGS`` is set.

    Returns:
        True if the flags are in effect for the backend that will start (False when opted
        out, or when JAX's backend had already started -- then nothing changes).
    """
    if not force and os.environ.get("UIMM_JAX_NO_XLA_FLAGS", "") not in ("", "0"):
        return False
    if _backend_started():
        return all(
            f.split("=")[0] in os.environ.get("XLA_FLAGS", "") for f in RECOMMENDED_XLA_FLAGS
        )
    current = os.environ.get("XLA_FLAGS", "")
    extra = [f for f in RECOMMENDED_XLA_FLAGS if f.split("=")[0] not in current]
    if extra:
        os.environ["XLA_FLAGS"] = " ".join([current, *extra]).strip()
    return True
