"""Test-session setup: the recommended XLA CPU flags (before JAX starts) and float64.

The library never changes JAX's configuration; the test session does, as the CLI does:
float64 is the reference precision.  float32 tests use ``jax.enable_x64(False)`` locally.
"""

from uimm_jax.xla_flags import apply_recommended_xla_flags

apply_recommended_xla_flags()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
