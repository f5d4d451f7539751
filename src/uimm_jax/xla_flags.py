"""XLA CPU flags that make the filter's time loop fast: applied at import, with an opt-out.

Two flags matter on the CPU (measured in benchmarks/README.md):

* ``--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=<large>`` lets
  XLA CPU hoist a whole ``lax.scan`` into one compiled kernel when its body has no dots
  or custom calls -- the engine's bank algebra is written that way
  (:mod:`uimm_jax.engine._block`).  Without it each step pays per-kernel dispatch:
  measured 6.5x slower for the block-form UIMM step (2.0 against 0.31 us/step).
* ``--xla_cpu_experimental_ynn_fusion_type=`` (empty) turns off the YNNPACK fusions that
  XLA CPU otherwise picks for batched multiply-reduce patterns from a batch of about 64
  runs, where throughput collapses.

Both are CPU-only; other backends ignore them.  XLA reads ``XLA_FLAGS`` once, when JAX's
backend starts, and a per-computation compiler option cannot carry the first (JAX 0.10
rejects ``xla_backend_extra_options`` in ``compiler_options``).  So ``import uimm_jax``
appends the missing flags to ``XLA_FLAGS`` -- only while no JAX backend has started, and
never touching ``jax.config``.  Opt out by setting ``UIMM_JAX_NO_XLA_FLAGS=1`` before the
import.  When the engine then runs on a CPU backend that started without the flags (JAX
was used before ``uimm_jax`` was imported), :func:`warn_if_slow` warns once.

The flags are added only when JAX will run on the CPU (:func:`cpu_backend_expected`):
``JAX_PLATFORMS`` (or ``JAX_PLATFORM_NAME``) names ``cpu`` first, or names nothing and no
accelerator plugin (``jax[cuda12]``, ROCm, TPU) is installed.  A GPU or TPU run leaves
``XLA_FLAGS`` as the user set it.  With a GPU plugin installed on a machine without a GPU,
JAX falls back to the CPU without the flags: set ``JAX_PLATFORMS=cpu`` there (the warning
of :func:`warn_if_slow` says so).

This module does not import JAX.
"""

from __future__ import annotations

import os
import sys
import warnings

__all__ = [
    "RECOMMENDED_XLA_FLAGS",
    "apply_recommended_xla_flags",
    "cpu_backend_expected",
    "flags_in_effect",
    "warn_if_slow",
]

RECOMMENDED_XLA_FLAGS = (
    "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000000",
    "--xla_cpu_experimental_ynn_fusion_type=",
)

_warned = False


def _backend_started() -> bool:
    xb = sys.modules.get("jax._src.xla_bridge")
    if xb is None:
        return False
    backends = getattr(xb, "_backends", None)
    return bool(backends)


def _opted_out() -> bool:
    return os.environ.get("UIMM_JAX_NO_XLA_FLAGS", "") not in ("", "0")


_PLUGIN_PREFIXES = ("jax_cuda", "jax_rocm", "libtpu")


def _accelerator_plugins() -> list[str]:
    """Installed JAX accelerator plugins (``jax_cuda*``, ``jax_rocm*``, ``libtpu``, plugins).

    A directory scan of ``sys.path``; JAX is not imported.
    """
    import importlib.util
    import pkgutil

    names = [m.name for m in pkgutil.iter_modules() if m.name.startswith(_PLUGIN_PREFIXES)]
    try:
        spec = importlib.util.find_spec("jax_plugins")
    except (ImportError, ValueError):
        spec = None
    if spec is not None and spec.submodule_search_locations:
        names += [m.name for m in pkgutil.iter_modules(spec.submodule_search_locations)]
    return names


def cpu_backend_expected(env=None) -> bool:
    """Whether JAX will run on its CPU backend, judged before any backend starts.

    Args:
        env: the environment (default ``os.environ``).

    Returns:
        True when ``JAX_PLATFORMS`` (else ``JAX_PLATFORM_NAME``) lists ``cpu`` first, or
        when neither is set and no accelerator plugin is installed.
    """
    env = os.environ if env is None else env
    platforms = env.get("JAX_PLATFORMS", "").strip() or env.get("JAX_PLATFORM_NAME", "").strip()
    if platforms:
        return platforms.split(",")[0].strip().lower() == "cpu"
    return not _accelerator_plugins()


def flags_in_effect() -> bool:
    """True when ``XLA_FLAGS`` holds every recommended flag."""
    current = os.environ.get("XLA_FLAGS", "")
    return all(f.split("=")[0] in current for f in RECOMMENDED_XLA_FLAGS)


def apply_recommended_xla_flags(*, force: bool = False) -> bool:
    """Append the recommended flags to ``XLA_FLAGS`` unless opted out or already set.

    Args:
        force: apply even if ``UIMM_JAX_NO_XLA_FLAGS`` is set or JAX will not run on the
            CPU.

    Returns:
        True if the flags are in effect for the backend that will start (False when opted
        out, when JAX will run on an accelerator (:func:`cpu_backend_expected`), or when
        JAX's backend had already started without them -- then nothing changes).
    """
    if not force and (_opted_out() or not cpu_backend_expected()):
        return False
    if _backend_started():
        return flags_in_effect()
    current = os.environ.get("XLA_FLAGS", "")
    extra = [f for f in RECOMMENDED_XLA_FLAGS if f.split("=")[0] not in current]
    if extra:
        os.environ["XLA_FLAGS"] = " ".join([current, *extra]).strip()
    return True


def warn_if_slow() -> None:
    """Warn once if the engine runs on a CPU backend that started without the flags.

    Called by the time-loop drivers; silent when opted out (the user chose), on other
    backends, or when the flags are in effect.
    """
    global _warned
    if _warned or _opted_out() or flags_in_effect():
        return
    import jax

    if jax.default_backend() != "cpu":
        return
    _warned = True
    from uimm_jax.errors import UIMMWarning

    warnings.warn(
        "JAX's CPU backend started before uimm_jax could set its XLA flags, so the time "
        "loop runs several times slower (one kernel per step). Import uimm_jax before "
        "using JAX (with an accelerator plugin installed on a machine without one, also set "
        "JAX_PLATFORMS=cpu), or set XLA_FLAGS to include "
        + " ".join(RECOMMENDED_XLA_FLAGS)
        + " (set UIMM_JAX_NO_XLA_FLAGS=1 to silence this).",
        UIMMWarning,
        stacklevel=3,
    )
