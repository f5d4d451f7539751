"""Gathered cache rebuilds of the size-estimating UIMM (:mod:`uimm_jax.engine.uimm_est`).

Internal: a rebuild runs only for the runs of a batch that need one, gathered into a
group of :data:`REBUILD_GROUPS` when they fit, and a run's numbers are those of the
whole-batch rebuild, bit for bit (docs/faults.md, "Cost").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

REBUILD_GROUPS = (8, 32)
"""Sizes of the gathered rebuilds (:func:`gathered`; docs/faults.md, "Cost")."""


def gathered(fn, need: jax.Array, args: tuple, old, group: int):
    """``fn(*args)`` on the (at most ``group``) runs where ``need``, ``old`` on the others.

    ``need`` is ``(*runs,)``; every leaf of ``args`` and of ``old`` (the result's pytree)
    ends with the run axes, and ``fn`` works run by run.  The runs in need are gathered
    into a batch of ``group`` and each pulls its own result back (selects only): a run's
    result is the one ``fn`` gives on the whole batch, bit for bit.
    """
    r = need.ndim
    R = need.size
    flat = lambda x: x.reshape(x.shape[: x.ndim - r] + (R,))
    need_f = need.reshape(R)
    # A run's slot: how many runs before it need one (a triangular count, not cumsum or
    # nonzero, which cost more than the rebuild inside the compiled step; measured).
    if R <= 1024:
        before = np.tril(np.ones((R, R), bool), -1)  # [r, q]: q < r
        pos = jnp.sum(before & need_f[None], axis=1)  # (R,)
    else:  # the same numbers without an R x R mask
        pos = jnp.cumsum(need_f.astype(jnp.int32)) - need_f
    slot = need_f[None] & (pos[None] == np.arange(group)[:, None])  # (group, R)
    idx = jnp.argmax(slot, axis=1)  # the run in each slot (0 for an empty slot: unused)
    fresh = fn(*jax.tree.map(lambda x: jnp.take(flat(x), idx, axis=-1), args))
    pos = jnp.minimum(pos, group - 1)
    pull = lambda o, f: jnp.where(need_f, jnp.take(f, pos, axis=-1), flat(o)).reshape(o.shape)
    return jax.tree.map(pull, old, fresh)


def per_run(need: jax.Array):
    """``(fresh, old) -> fresh`` on the runs where ``need``, else ``old`` (runs trailing)."""

    def pick(fresh, old):
        r = need.ndim
        if r and fresh.ndim >= r and fresh.shape[fresh.ndim - r :] == need.shape:
            return jnp.where(need, fresh, old)
        return fresh  # a leaf without the run axes does not depend on the run

    return pick
