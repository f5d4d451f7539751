"""The run figure of mode probabilities with what a reader needs to follow it.

:func:`plot_mode_probabilities_detail` draws paper Figs. 6/8 (all samples, decimated) and,
under it, one zoom panel of ``±zoom_s`` seconds around each true onset at full
resolution, where the transient and the detection delay can be seen (at 100 s scale a
39 ms delay is invisible).  For the UIMM, whose model 0 is "D, the declared set", the
content of D after each declaration is written on the plot (a reader expecting the
paper's Fig. 6, where model 2 takes over at 30 s, sees model 0 take over instead, and
why).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from uimm_jax.studies.plots import _as_2d, _check_t, draw_mode_probabilities

__all__ = ["declared_set_labels", "plot_mode_probabilities_detail"]


def declared_set_labels(declarations: Sequence[tuple[float, str]]) -> list[tuple[float, str]]:
    """``(time, "D = {a, b}")`` after each declaration time (faults declared together merge)."""
    out: list[tuple[float, str]] = []
    declared: list[str] = []
    for time, name in sorted(declarations):
        declared.append(name)
        label = "D = {" + ", ".join(declared) + "}"
        if out and out[-1][0] == time:
            out[-1] = (time, label)
        else:
            out.append((time, label))
    return out


def plot_mode_probabilities_detail(
    t,
    mode_probs,
    model_labels: Sequence[str],
    *,
    events: Sequence[tuple[float, str]] = (),
    declarations: Sequence[tuple[float, str]] = (),
    declared_sets: Sequence[tuple[float, str]] = (),
    delays: Mapping[str, float | None] | None = None,
    zoom_s: float | None = 0.5,
    title: str | None = None,
) -> Figure:
    """Mode probabilities over the whole run, with zoom panels around the true onsets.

    Args:
        t: Time stamps in seconds, shape (N,).
        mode_probs: Mode probabilities, shape (N, M).
        model_labels: Name of each of the M models.
        events: True fault onsets ``(time, fault)``.
        declarations: Declarations ``(time, fault)``.
        declared_sets: ``(time, text)`` notes written at the top of the main panel from
            ``time`` on, e.g. :func:`declared_set_labels` (the UIMM's model 0 is D).
        delays: Detection delay of each fault in s (``summary["detection_delay_s"]``),
            written over its zoom panel; default: declaration time minus onset.
        zoom_s: Half-width of each zoom panel in seconds; ``None`` or 0 for none.
        title: Figure title.

    Returns:
        The figure: the main axes first, then one axes per onset inside the data.
    """
    probs = _as_2d(np.asarray(mode_probs, float))
    t = _check_t(t, probs)
    if len(model_labels) != probs.shape[1]:
        raise ValueError(f"{len(model_labels)} model labels for {probs.shape[1]} models")
    end = float(t[-1]) if len(t) else 0.0
    onsets = sorted((time, name) for time, name in events if time <= end)
    zooms = onsets if zoom_s and len(t) > 1 else []
    fig = Figure(figsize=(10.0, 4.4 + (2.8 if zooms else 0.0)), layout="constrained")
    gs = fig.add_gridspec(
        2 if zooms else 1, max(len(zooms), 1), height_ratios=[1.5, 1] if zooms else [1]
    )
    ax = fig.add_subplot(gs[0, :])
    draw_mode_probabilities(ax, t, probs, model_labels, events=events, declarations=declarations)
    _write_declared_sets(ax, t, declared_sets)
    ax.set_title(title if title is not None else "Mode probabilities (cf. paper Figs. 6/8)")
    for i, (onset, name) in enumerate(zooms):
        lo, hi = np.searchsorted(t, [onset - zoom_s, onset + zoom_s])
        sl = slice(max(lo - 1, 0), min(hi + 1, len(t)))
        axz = fig.add_subplot(gs[1, i])
        draw_mode_probabilities(
            axz, t[sl], probs[sl], model_labels, events=events, declarations=declarations
        )
        axz.get_legend().remove()
        later = [d - onset for d, f in declarations if f == name and d >= onset]
        dly = (delays or {}).get(name, min(later) if later else None)
        delay = f": declared after {dly * 1e3:.1f} ms" if dly is not None else ": not declared"
        axz.set_title(f"{name} onset ± {zoom_s:g} s{delay}", fontsize=9)
        axz.tick_params(labelsize=8)
        axz.xaxis.label.set_size(8)
        axz.yaxis.label.set_size(8)
    return fig


def _write_declared_sets(ax, t, declared_sets) -> None:
    """Write what D holds from each declaration on, at the top of the main panel."""
    if not len(t):
        return
    for time, text in declared_sets:
        if t[0] <= time <= t[-1]:
            ax.annotate(
                text,
                (time, 0.985),
                xycoords=("data", "axes fraction"),
                xytext=(4, 0),
                textcoords="offset points",
                ha="left",
                va="top",
                fontsize=8,
                color="C0",
                bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "C0", "alpha": 0.85},
            )
