"""Figure of the estimated fault parameters against the truth (size-estimating diagnoser).

The paper's abstract says the key physical parameters "can be estimated by employing a
series of extended Kalman filters"; ``uimm-est`` does, and this figure shows it: for each
declared fault, each parameter it changes, in physical units, estimated (with its 95 %
interval) and true, over time.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from uimm_jax.engine.bank import FaultTable, param_at_magnitude
from uimm_jax.engine.uimm_est import Z95

__all__ = ["plot_fault_parameters"]


def plot_fault_parameters(
    t: np.ndarray,
    magnitude: np.ndarray,
    magnitude_sd: np.ndarray,
    true_magnitude: np.ndarray,
    declared: np.ndarray,
    table: FaultTable,
    param_names: Sequence[str],
    *,
    title: str | None = None,
    max_points: int = 4000,
) -> Figure:
    """One panel per parameter of each fault ever declared: estimate, 95 % band, truth.

    Args:
        t: ``(N,)`` times (s).
        magnitude: ``(N, F)`` estimated magnitudes.
        magnitude_sd: ``(N, F)`` their standard deviations.
        true_magnitude: ``(N, F)`` true magnitudes (0: absent).
        declared: ``(N,)`` declared-set codes (bit j = fault j); the estimate is drawn
            solid while the fault is declared, thin while it is only a hypothesis.
        table: the fault table (nominal and library values, scales).
        param_names: the plant's parameter names.
        title: figure title.
        max_points: samples drawn per curve (evenly strided).

    Returns:
        The figure.
    """
    t = np.asarray(t, float)
    step = max(1, len(t) // max_points)
    sl = slice(None, None, step)
    codes = np.asarray(declared, np.int64)
    faults = [j for j in range(table.num_faults) if np.any(codes & (1 << j))]
    panels = [(j, q) for j in faults for q in np.flatnonzero(table.mask[j])]
    fig = Figure(figsize=(9.0, 2.4 * max(len(panels), 1) + 0.6), layout="constrained")
    if not panels:
        ax = fig.add_subplot(1, 1, 1)
        ax.text(0.5, 0.5, "no fault declared", ha="center", va="center")
        ax.set_axis_off()
        return fig
    log = table.log_mask
    for i, (j, q) in enumerate(panels):
        ax = fig.add_subplot(len(panels), 1, i + 1)
        v0, v1 = table.nominal[q], table.values[j, q]

        def phys(a, v0=v0, v1=v1, lg=log[q]):
            return param_at_magnitude(v0, v1, a, lg, np)

        m = magnitude[sl, j]
        lo = phys(m - Z95 * magnitude_sd[sl, j])
        hi = phys(m + Z95 * magnitude_sd[sl, j])
        on = (codes[sl] & (1 << j)) > 0
        est = phys(m)
        ax.fill_between(
            t[sl],
            np.minimum(lo, hi),
            np.maximum(lo, hi),
            where=on,
            color="C1",
            alpha=0.25,
            lw=0,
            label="95 % interval",
        )
        ax.plot(t[sl], np.where(on, est, np.nan), color="C1", lw=1.2, label="estimate")
        ax.plot(
            t[sl],
            np.where(on, np.nan, est),
            color="C1",
            lw=0.4,
            alpha=0.4,
            label="hypothesis (not declared)",
        )
        ax.plot(t[sl], phys(true_magnitude[sl, j]), color="k", lw=1.2, ls="--", label="truth")
        ax.set_ylabel(f"{param_names[q]} ({table.names[j]})", fontsize=9)
        ax.grid(True, alpha=0.3)
        if i == 0:
            ax.legend(loc="best", fontsize=8)
    fig.axes[-1].set_xlabel("time (s)")
    fig.suptitle(title or "Estimated fault parameters vs truth")
    return fig
