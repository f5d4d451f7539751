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


def test_declare_trend_refuses_an_estimate_projected_below_declare_min():
    """With ``declare_trend = H`` a new declaration also needs ``est + H min(trend, 0) >=
    declare_min`` (docs/faults.md, "Session 27"): a falling estimate is refused, a rising or
    steady one is not, and a declared fault is not a new declaration (``cand_set``)."""
    H, s = 500, EstSettings(declare_trend=500, declare_rel=0.0)
    # one fault x runs: falling fast (sim 2's leakage look-alike), falling slowly,
    # steady, rising, and falling fast from far above declare_min
    est = jnp.asarray([[0.19, 0.19, 0.19, 0.16, 0.5]])
    trend = jnp.asarray([[-2.2e-4, -5e-5, 0.0, 3e-4, -2.2e-4]])
    declared = jnp.zeros(est.shape, bool)
    sd = jnp.full(est.shape, 0.01)
    got = np.asarray(declarable(s, declared, est, sd, trend))
    want = np.asarray(est + H * np.minimum(trend, 0.0) >= s.declare_min)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got[0], [False, True, True, True, True])
    off = declarable(EstSettings(declare_rel=0.0, declare_trend=0), declared, est, sd, trend)
    np.testing.assert_array_equal(np.asarray(off[0]), [True] * 5)


def test_declare_rel_next_refuses_a_loose_estimate_only_while_a_fault_is_declared():
    """``declare_rel_next`` (session 27, off by default) is ``declare_rel`` for the later
    declarations: with a fault declared a new one needs ``sd <= declare_rel_next * est``;
    with nothing declared only ``declare_rel`` counts."""
    # faults (valve wear, leakage) x runs: valve wear declared in runs 0-2; leakage tight
    # (0.02 of 0.3), loose (0.03 of 0.3), loose but nothing declared (run 3)
    declared = jnp.asarray([[True, True, True, False], [False, False, False, False]])
    est = jnp.asarray([[0.5, 0.5, 0.5, 0.05], [0.3, 0.3, 0.37, 0.3]])
    sd = jnp.asarray([[0.01, 0.01, 0.01, 0.5], [0.02, 0.03, 0.039, 0.03]])
    s = EstSettings(declare_rel_next=0.08, declare_trend=0)
    got = np.asarray(declarable(s, declared, est, sd)[1])
    np.testing.assert_array_equal(got, [True, False, False, True])
    off = np.asarray(declarable(s._replace(declare_rel_next=0.0), declared, est, sd)[1])
    np.testing.assert_array_equal(off, [True, True, True, True])
    assert EstSettings().declare_rel_next == 0.0  # off by default
