"""Figure of the innovation check over time: each measured output's mean NIS per window.

``summary.json``'s ``innovation_check`` gives one mean per output over the whole run;
this figure shows *when* an output's innovations leave the band: a noise set wrong from
the start (the whole curve away from 1), or a change the bank does not model (the curve
leaves 1 at that time and stays).  Each panel is one output's ``e_i^2 / S_ii`` of the most
probable model (:func:`uimm_jax.engine.scan.leading_nis_channels`), averaged over
consecutive windows of samples, with the consistent value 1, the band
:data:`uimm_jax.engine.metrics.NIS_BAND` that the check calls consistent, and the 99 %
sampling band of one window's mean under consistency (``1 +- 2.576 sqrt(2 / w)``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from uimm_jax.engine.innovation import window_sums
from uimm_jax.engine.metrics import NIS_BAND

__all__ = ["plot_innovation", "window_means"]


def window_means(nis_channels: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Means of ``(N, m)`` per-output NIS over consecutive windows of ``window`` samples.

    NaN entries (the output missing) are left out of their window's mean; a window with
    no observed sample gives NaN.  The last, partial window is kept.  Returns the first
    sample index of each window ``(W,)`` and the means ``(W, m)``.
    """
    a = np.asarray(nis_channels, np.float64)
    window = max(1, int(window))
    sums, counts = window_sums(a.reshape(a.shape[0], -1), window)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return np.arange(sums.shape[0]) * window, means


def plot_innovation(
    t: np.ndarray,
    nis_channels: np.ndarray,
    output_names: Sequence[str],
    *,
    events: Sequence[tuple[float, str]] = (),
    declarations: Sequence[tuple[float, str]] = (),
    window: int | None = None,
    title: str | None = None,
) -> Figure:
    """One panel per measured output: its mean NIS per window against 1 and the bands.

    Args:
        t: ``(N,)`` sample times (s).
        nis_channels: ``(N, m)`` the leading model's ``e_i^2 / S_ii`` (NaN: missing).
        output_names: the ``m`` output names.
        events: ``(time, fault)`` of the truth's events (dashed lines).
        declarations: ``(time, fault)`` of the declarations (dotted lines).
        window: samples per window; default ``max(50, N // 400)`` (about 400 points).
        title: figure title.

    Returns:
        The figure.
    """
    t = np.asarray(t, np.float64)
    N = t.shape[0]
    window = max(50, N // 400) if window is None else int(window)
    ch = np.asarray(nis_channels, np.float64).reshape(N, -1)
    start, means = window_means(ch, window)
    tw = t[np.minimum(start + window // 2, N - 1)]
    m = means.shape[1]
    fig = Figure(figsize=(9.0, 1.9 * m + 0.8), layout="constrained")
    axes = fig.subplots(m, 1, sharex=True, squeeze=False)[:, 0]
    half = 2.5758293035489004 * np.sqrt(2.0 / window)
    lo, hi = NIS_BAND
    for i, ax in enumerate(axes):
        ax.axhspan(lo, hi, color="tab:green", alpha=0.12, lw=0, label="consistent (check's band)")
        ax.axhspan(
            1.0 - half, 1.0 + half, color="tab:green", alpha=0.18, lw=0, label="99 % of a window"
        )
        ax.axhline(1.0, color="tab:green", lw=0.8)
        ax.plot(tw, means[:, i], color="tab:blue", lw=1.0, label=f"mean per {window} samples")
        for k, (te, _) in enumerate(events):
            ax.axvline(te, color="0.4", ls="--", lw=0.8, label=None if k else "fault event")
        for k, (td, _) in enumerate(declarations):
            ax.axvline(td, color="tab:red", ls=":", lw=0.8, label=None if k else "declaration")
        finite = means[np.isfinite(means[:, i]), i]
        top = max(2.0, float(np.max(finite)) * 1.1) if finite.size else 2.0
        if top > 20.0:  # far off: a log scale keeps the band of 1 in view
            ax.set_yscale("log")
            ax.set_ylim(min(0.5, float(np.min(finite)) / 1.5), top * 1.5)
        else:
            ax.set_ylim(0.0, top)
        name = output_names[i] if i < len(output_names) else str(i)
        seen = ch[np.isfinite(ch[:, i]), i]
        note = f"run mean {float(np.mean(seen)):.3g}" if seen.size else "never observed"
        ax.set_ylabel(f"{name}\nNIS")
        ax.text(0.005, 0.95, note, transform=ax.transAxes, va="top", fontsize=8)
    axes[0].legend(loc="upper right", fontsize=7, ncols=3)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(
        title or "Innovation check by output: 1 when the filter's noise fits the data",
        fontsize=10,
    )
    return fig
