"""The decision rule, paper eq. (29) with persistence, shared by every diagnoser.

Let ``c`` be the most probable model after the update.  If ``mu_c >= threshold`` and
``c``'s fault set holds a fault not yet declared, a run counter for ``c`` grows by one per
sample (it restarts when ``c`` changes or the condition fails); when it reaches ``hold``
the faults of ``c`` are *declared*.  Declared faults never retract (faults are
irreversible, paper section 3.3).

A diagnoser supplies the fault set of the candidate (``candidate_set``): UIMM's model
``c > 0`` is ``D + f_c``, the combinatorial IMM's model ``c`` is the subset whose bits
``c`` holds.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["Decision", "decide"]


class Decision(NamedTuple):
    """Outcome of one application of the decision rule (batch shape ``runs``).

    Attributes:
        candidate: ``(*runs,)`` int32, the most probable model ``c``.
        candidate_set: ``(F, *runs)`` bool, its fault set (the recognised system mode).
        declared: ``(F, *runs)`` bool, the declared set after this step.
        declared_now: ``(*runs,)`` bool, a declaration happened at this step.
        run_len: ``(*runs,)`` int32, the run counter after this step.
    """

    candidate: jax.Array
    candidate_set: jax.Array
    declared: jax.Array
    declared_now: jax.Array
    run_len: jax.Array


def decide(
    log_mu: jax.Array,
    candidate_set,
    declared: jax.Array,
    run_model: jax.Array,
    run_len: jax.Array,
    threshold: jax.Array,
    hold: jax.Array,
) -> Decision:
    """Apply eq. (29) with persistence.

    Args:
        log_mu: ``(M, *runs)`` posterior log mode probabilities.
        candidate_set: ``f(candidate (*runs,)) -> (F, *runs)`` bool, the fault set of a
            model (diagnoser specific).
        declared: ``(F, *runs)`` bool, the declared set before this step.
        run_model: ``(*runs,)`` int32, the model whose run counter is active.
        run_len: ``(*runs,)`` int32, its length.
        threshold: decision threshold ``mu_f`` on the mode probability.
        hold: persistence in samples.

    Returns:
        A :class:`Decision`.
    """
    cand = jnp.argmax(log_mu, axis=0).astype(jnp.int32)
    cand_set = candidate_set(cand)
    top = jnp.max(log_mu, axis=0)
    qualifies = jnp.any(cand_set & ~declared, axis=0) & (
        top >= jnp.log(jnp.asarray(threshold, log_mu.dtype))
    )
    run_len = jnp.where(qualifies, jnp.where(cand == run_model, run_len + 1, 1), 0)
    now = qualifies & (run_len >= hold)
    new_declared = jnp.where(now, cand_set | declared, declared)
    run_len = jnp.where(now, 0, run_len).astype(jnp.int32)
    return Decision(cand, cand_set, new_declared, now, run_len)
