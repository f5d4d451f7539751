"""Figures of the studies: Monte Carlo sweeps, confusion matrices and tuning loss curves.

Built like the run figures of :mod:`uimm_jax.studies.plots` (object API, no
:mod:`matplotlib.pyplot`, decimated curves); save them with
:func:`uimm_jax.studies.plots.save_figure`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from uimm_jax.studies.plots import _CYCLE, _decimate

__all__ = ["plot_confusion", "plot_loss_curve", "plot_sweep"]


def plot_sweep(cells: Sequence[Mapping], *, title: str | None = None) -> Figure:
    """Plot Monte Carlo detection performance against fault magnitude.

    Left panel: detection probability per fault and method, with confidence-interval
    error bars when a cell gives ``"detection_probability_ci"``. Right panel: median
    detection delay (cells where it is None are skipped). Colour encodes the fault,
    line style and marker the method. The paper has no such figure; it extends the
    single runs of Figs. 6-9 to many seeds and fault magnitudes.

    Args:
        cells: One dict per (method, magnitude) cell with keys ``"method"`` (str),
            ``"magnitude"`` (float), ``"detection_probability"`` (fault -> float),
            optionally ``"detection_probability_ci"`` (fault -> [lo, hi]) and
            ``"median_delay_s"`` (fault -> float or None).
        title: Figure title; a default is used when None.

    Returns:
        The figure (two axes side by side).
    """
    methods: list[str] = []
    faults: list[str] = []
    for cell in cells:
        if cell["method"] not in methods:
            methods.append(cell["method"])
        for fault in cell["detection_probability"]:
            if fault not in faults:
                faults.append(fault)
    markers = ["o", "s", "^", "D", "v", "P", "X"]
    styles = ["-", "--", ":", "-."]

    fig = Figure(figsize=(11.0, 4.3), layout="constrained")
    ax_p, ax_d = fig.subplots(1, 2)
    delays_all = []
    legend: list = []  # handles in plotting order (errorbar containers sort last otherwise)
    for mi, method in enumerate(methods):
        mcells = sorted((c for c in cells if c["method"] == method), key=lambda c: c["magnitude"])
        for fi, fault in enumerate(faults):
            style = {
                "color": _CYCLE[fi % len(_CYCLE)],
                "ls": styles[mi % len(styles)],
                "marker": markers[mi % len(markers)],
                "ms": 5,
                "label": f"{fault} / {method}",
            }
            mag, p, lo, hi, dmag, dly = [], [], [], [], [], []
            for c in mcells:
                if fault in c["detection_probability"]:
                    pv = float(c["detection_probability"][fault])
                    mag.append(float(c["magnitude"]))
                    p.append(pv)
                    ci = (c.get("detection_probability_ci") or {}).get(fault)
                    lo.append(pv - float(ci[0]) if ci is not None else np.nan)
                    hi.append(float(ci[1]) - pv if ci is not None else np.nan)
                d = (c.get("median_delay_s") or {}).get(fault)
                if d is not None and np.isfinite(d):
                    dmag.append(float(c["magnitude"]))
                    dly.append(float(d))
            if mag:
                yerr = np.clip(np.array([lo, hi]), 0.0, None)
                if np.isnan(yerr).all():
                    legend.append(ax_p.plot(mag, p, **style)[0])
                else:
                    legend.append(
                        ax_p.errorbar(mag, p, yerr=np.nan_to_num(yerr), capsize=3, **style)
                    )
            if dmag:
                ax_d.plot(dmag, dly, **style)
                delays_all.extend(dly)

    ax_p.set_ylim(-0.03, 1.03)
    ax_p.set_xlabel("fault magnitude")
    ax_p.set_ylabel("detection probability")
    ax_p.grid(True, alpha=0.3)
    ax_p.set_title("Detection probability")
    ax_d.set_xlabel("fault magnitude")
    ax_d.set_ylabel("median detection delay (s)")
    ax_d.grid(True, which="both", alpha=0.3)
    ax_d.set_title("Median detection delay")
    pos = [d for d in delays_all if d > 0]
    if pos and len(pos) == len(delays_all) and max(pos) / min(pos) > 50:
        ax_d.set_yscale("log")
    if legend:
        ax_p.legend(legend, [h.get_label() for h in legend], fontsize=8)
    fig.suptitle(title if title is not None else "Monte Carlo sweep over fault magnitude")
    return fig


def plot_confusion(
    matrix: np.ndarray,
    row_labels: Sequence[str],
    col_labels: Sequence[str],
    *,
    title: str | None = None,
) -> Figure:
    """Plot a confusion matrix (true fault x declared fault) as an annotated heat map.

    Args:
        matrix: Counts (or rates), shape (R, C); rows are true faults, columns declared.
        row_labels: The R true-fault names.
        col_labels: The C declared-fault names.
        title: Figure title; a default is used when None.

    Returns:
        The figure (heat map plus colour bar).
    """
    matrix = np.asarray(matrix)
    if matrix.ndim != 2:
        raise ValueError(f"matrix must be 2-D, got shape {matrix.shape}")
    r, c = matrix.shape
    if len(row_labels) != r or len(col_labels) != c:
        raise ValueError(f"{len(row_labels)} x {len(col_labels)} labels for a {r} x {c} matrix")
    values = matrix.astype(float)
    fig = Figure(figsize=(1.2 + 1.1 * c + 1.5, 1.2 + 0.7 * r + 0.8), layout="constrained")
    ax = fig.add_subplot()
    im = ax.imshow(values, cmap="Blues", vmin=0.0, aspect="auto")
    fig.colorbar(im, ax=ax, shrink=0.9)
    finite = values[np.isfinite(values)]
    vmax = float(finite.max()) if finite.size else 0.0
    integral = np.all(np.isfinite(values)) and np.allclose(values, np.round(values))
    for i in range(r):
        for j in range(c):
            v = values[i, j]
            text = f"{int(round(v))}" if integral else f"{v:.3g}"
            colour = "white" if vmax > 0 and v > 0.5 * vmax else "black"
            ax.text(j, i, text, ha="center", va="center", color=colour, fontsize=10)
    ax.set_xticks(range(c), list(col_labels), rotation=30, ha="right")
    ax.set_yticks(range(r), list(row_labels))
    ax.set_xlabel("declared fault")
    ax.set_ylabel("true fault")
    ax.set_title(title if title is not None else "Confusion matrix")
    return fig


def plot_loss_curve(
    history: np.ndarray | Mapping[str, np.ndarray], *, title: str | None = None
) -> Figure:
    """Plot a tuning loss against the optimiser iteration.

    Args:
        history: Loss per iteration, shape (K,), or a mapping from a curve name (e.g.
            ``"train"``, ``"validation"``) to such an array.
        title: Figure title; a default is used when None.

    Returns:
        The figure (one axes; log y scale when the loss is positive and spans more
        than two decades).
    """
    curves = (
        {str(k): np.asarray(v, dtype=float) for k, v in history.items()}
        if isinstance(history, Mapping)
        else {"loss": np.asarray(history, dtype=float)}
    )
    fig = Figure(figsize=(6.5, 4.0), layout="constrained")
    ax = fig.add_subplot()
    finite = []
    for name, loss in curves.items():
        it, ld = _decimate(np.arange(loss.shape[0]), loss)
        ax.plot(it, ld, lw=1.2, label=name)
        finite.append(loss[np.isfinite(loss)])
    allv = np.concatenate(finite) if finite else np.zeros(0)
    if allv.size and allv.min() > 0 and allv.max() / allv.min() > 100:
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.grid(True, which="both", alpha=0.3)
    if len(curves) > 1:
        ax.legend()
    ax.set_title(title if title is not None else "Tuning loss")
    return fig
