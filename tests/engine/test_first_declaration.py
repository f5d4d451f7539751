"""uimm-est's first declaration: ``declare_rel`` (docs/faults.md, "Session 11"; 0.15 by default)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from uimm_jax.engine._est_rules import declarable
from uimm_jax.engine.uimm_est import EstSettings


def test_declare_rel_refuses_a_loose_estimate_only_while_nothing_is_declared():
    """With ``declare_rel`` a first declaration needs ``sd <= declare_rel * est`` as well as
    ``est >= declare_min``; once a fault is declared only ``declare_min`` counts."""
    # faults (valve wear, leakage) x runs: run 0 nothing declared, a tight leakage (sd 0.05
    # of 0.3); run 1 nothing declared, a loose one (0.09 of 0.3); run 2 nothing declared,
    # tight but below declare_min; run 3 valve wear declared, a loose leakage.
    declared = jnp.asarray([[False, False, False, True], [False, False, False, False]])
    est = jnp.asarray([[0.05, 0.05, 0.05, 0.5], [0.3, 0.3, 0.1, 0.3]])
    sd = jnp.asarray([[0.5, 0.5, 0.5, 0.01], [0.05, 0.09, 0.001, 0.09]])
    on = declarable(EstSettings(declare_rel=0.2), declared, est, sd)
    off = declarable(EstSettings(declare_rel=0.0), declared, est, sd)
    np.testing.assert_array_equal(on[1], [True, False, False, True])
    np.testing.assert_array_equal(off[1], [True, True, False, True])
    np.testing.assert_array_equal(on[0], [False, False, False, True])
