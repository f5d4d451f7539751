"""The size-estimating UIMM's estimates' trends: ``drift_walk`` and ``declare_trend``.

Internal (:mod:`uimm_jax.engine.uimm_est`): an exponential average of each estimate's
change per step, and the two rules that read it: a walk that follows a growing
estimate (``drift_walk``) and a new declaration refused to an estimate that is falling
towards nominal (``declare_trend``, read by :func:`uimm_jax.engine._est_rules.declarable`).
Arrays have the fault axis leading and the model and run axes trailing.
"""

from __future__ import annotations

import jax.numpy as jnp

from uimm_jax.engine._est_rules import add_mag_var, own_slots
from uimm_jax.engine.imm import IMMState
from uimm_jax.engine.uimm_est_types import EstSettings

DRIFT_CLIP = 5e-3
"""Largest move of an estimate in one step that :func:`drift_update` counts (per sample,
as the walks): a ramp to 3 over 0.06 s at ``dt`` = 1e-4 s.  An abrupt fault's estimate
jumps by up to its size in a few steps; counted whole, its drift would open a walk of
tenths per step and hold the first declaration back (``declare_rel``)."""


DRIFT_WAIT = 5
"""An undeclared hypothesis counts its estimate's moves in ``drift_walk``'s average once
it has run ``DRIFT_WAIT * drift_steps`` steps since its last restart (:func:`drift_update`)."""


def drift_update(s: EstSettings, drift, move, fresh, steps=None):
    """An estimate's average move: ``drift + (clip(move) - drift) / steps``.

    ``move`` ``(F, *runs)`` is this step's change of each estimate by the IMM cycle (the
    filter's correction, after the rules' restarts and walks), clipped to
    ``+-DRIFT_CLIP``; an exponential average over ``steps`` steps (``drift_steps`` for
    ``drift_walk``'s ``EstState.drift``; :func:`trend_steps` for ``declare_trend``'s
    ``EstState.trend``, whose caller passes its own wait as ``fresh``).  A hypothesis
    that restarted from the prior within the last ``DRIFT_WAIT * drift_steps`` steps
    (``fresh``) keeps 0: its estimate's moves are the prior's distance to the data, not a
    growth (counted from 20 steps on, a look-alike restarted at a fault's onset converged
    from the prior for 50 steps under a growing walk and won: sim 2's abrupt air in oil
    at 0.3, run 9 of 64, leakage declared at 4.8).
    """
    new = drift + (jnp.clip(move, -DRIFT_CLIP, DRIFT_CLIP) - drift) / (steps or s.drift_steps)
    return jnp.where(fresh, 0.0, new)


def drift_walk(s: EstSettings, n: int, st: IMMState, declared, drift, since) -> IMMState:
    """A fault's walk follows its estimate's growth: sd ``max(walk, drift_walk d)``.

    ``d`` (``EstState.drift``) is the estimate's change per step averaged over
    ``drift_steps`` steps, counted away from nominal only (a fault grows, and ends
    abruptly: a fall is the retraction hypothesis' business).  The walk sets how fast a
    filter can follow its fault: at ``walk`` = 1e-3 per step a ramp to 1 over 0.1 s
    (1e-3 per step) is followed with a lag, and a look-alike restarted from the prior
    wins the race; a larger fixed walk lets look-alikes fit as well as the truth once the
    fault stops (docs/faults.md, "Ramps", "Session 19").  The extra variance is added to
    a declared fault's magnitude in every model and to an undeclared one in its own
    hypothesis.  With ``drift_lead`` only where a growth is being led: to the undeclared
    hypothesis that leads the other undeclared ones (highest mode probability at the
    step's start), and to a declared fault until it settles (``since``, its age, below
    ``settle_steps``; restarted by its growth only where
    :func:`~uimm_jax.engine._est_rules.growth_ages` holds, as on the defaults).  A
    look-alike's walk, widened by the noise of its moves, let it fit as well as the
    truth and held the first declaration back; a settled fault's walk,
    opened by the noise of its estimate, lowered air in oil's coverage on sim 2's 10 s
    ramps at 2 by 3 points (docs/faults.md, "Ramps", "Session 22").  Adds a PSD matrix.
    """
    F = declared.shape[0]
    sd = jnp.maximum(s.walk, s.drift_walk * jnp.maximum(drift, 0.0))  # (F, *runs)
    own = own_slots(F, declared.ndim - 1)  # (F, M, *runs)
    walked = declared
    if s.drift_lead:  # the leading undeclared hypothesis; declared faults still growing
        lp = jnp.where(declared, -jnp.inf, st.log_mode_probs[1:])  # (F, *runs)
        lead = ~declared & (lp == jnp.max(lp, axis=0))
        own = own & lead[:, None]
        walked = declared & (since < s.settle_steps)
    where = walked[:, None] | own
    extra = jnp.where(where, (sd**2 - s.walk**2)[:, None], 0.0)
    return st._replace(cov=add_mag_var(st.cov, n, extra))


def trend_steps(s: EstSettings) -> int:
    """``declare_trend``'s average, and its wait after a restart: a fifth of it (steps)."""
    return max(1, s.declare_trend // 5)
