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

__all__ = ["plot_confusion", "plot_confusion_grid", "plot_loss_curve", "plot_sweep"]


_METHOD_STYLE = [  # method 0, 1, ...: filled circles / hollow squares, solid / dashed
    {"marker": "o", "ls": "-", "mfc": None},
    {"marker": "s", "ls": "--", "mfc": "white"},
    {"marker": "^", "ls": ":", "mfc": None},
    {"marker": "D", "ls": "-.", "mfc": "white"},
]
_METHOD_GREY = ["k", "0.45", "0.25", "0.65"]


def _get(cell: Mapping, key: str, fault: str | None = None):
    v = cell.get(key)
    if fault is not None:
        v = (v or {}).get(fault)
    return None if v is None or not np.isfinite(float(v)) else float(v)


def plot_sweep(
    cells: Sequence[Mapping],
    *,
    fault_free: Sequence[Mapping] = (),
    title: str | None = None,
) -> Figure:
    """Plot Monte Carlo detection, isolation and false-alarm metrics against magnitude.

    Six panels: detection probability and median detection delay per fault (colour) and
    method (marker and line style: UIMM filled circles and solid lines, IMM hollow squares
    and dashed lines, the methods nudged apart so that equal values stay visible);
    isolation accuracy, false declarations per run, mode accuracy and the standard rates
    TDR / FAR / FIA per method.  Wilson intervals are drawn where the cells give them.
    With a single magnitude the x axis lists the methods (a dot chart) instead of one
    point on an empty magnitude axis.  ``fault_free`` cells (magnitude 0) add dotted
    reference lines (their false declarations per run, FAR and mode accuracy).  The
    paper has no such figure; it extends the single runs of Figs. 6-9 to many seeds.

    Args:
        cells: One dict per (method, magnitude) cell, as ``results.json`` cells: keys
            ``"method"``, ``"magnitude"``, ``"detection_probability"`` (fault -> float)
            and optionally ``"detection_probability_ci"``, ``"median_delay_s"``,
            ``"isolation_accuracy"`` (+ ``"_ci"``), ``"false_declarations"`` with
            ``"runs"``, ``"mode_accuracy"``, ``"tdr"``, ``"far"``, ``"fia"``.
        fault_free: The fault-free cells of the same methods (optional).
        title: Figure title; a default is used when None.

    Returns:
        The figure (six axes, 2 x 3).
    """
    methods: list[str] = []
    faults: list[str] = []
    for cell in cells:
        if cell["method"] not in methods:
            methods.append(cell["method"])
        for fault in cell["detection_probability"]:
            if fault not in faults:
                faults.append(fault)
    mags = sorted({float(c["magnitude"]) for c in cells})
    single = len(mags) <= 1
    span = (mags[-1] - mags[0]) if not single else 1.0
    nudge = 0.012 * span if not single else 0.12

    def xpos(cell, mi, k=0, n=1):
        """The x of a cell: magnitude nudged by method, or method index nudged by series k."""
        if single:
            return mi + (k - (n - 1) / 2) * nudge
        return float(cell["magnitude"]) + (mi - (len(methods) - 1) / 2) * nudge

    fig = Figure(figsize=(14.0, 7.6), layout="constrained")
    (ax_p, ax_d, ax_i), (ax_f, ax_m, ax_r) = fig.subplots(2, 3)
    legend: list = []
    delays_all: list[float] = []

    def series(ax, pts, style, err=None):
        """Plot ``[(x, y)]`` (sorted by x) with optional ``[(lo, hi)]`` intervals."""
        if not pts:
            return None
        x, y = zip(*pts, strict=True)
        kw = dict(style)
        if single:
            kw["ls"] = "none"
        if err is not None and not all(e is None for e in err):
            lo = [yy - e[0] if e else 0.0 for yy, e in zip(y, err, strict=True)]
            hi = [e[1] - yy if e else 0.0 for yy, e in zip(y, err, strict=True)]
            yerr = np.clip(np.array([lo, hi]), 0.0, None)
            return ax.errorbar(x, y, yerr=yerr, capsize=3, **kw)
        return ax.plot(x, y, **kw)[0]

    for mi, method in enumerate(methods):
        ms = _METHOD_STYLE[mi % len(_METHOD_STYLE)]
        mcells = sorted((c for c in cells if c["method"] == method), key=lambda c: c["magnitude"])
        for fi, fault in enumerate(faults):
            colour = _CYCLE[fi % len(_CYCLE)]
            style = {
                "color": colour,
                "ls": ms["ls"],
                "marker": ms["marker"],
                "ms": 6,
                "mfc": ms["mfc"] or colour,
                "label": f"{fault} / {method.upper()}",
            }
            p = [
                (xpos(c, mi, fi, len(faults)), _get(c, "detection_probability", fault), c)
                for c in mcells
                if _get(c, "detection_probability", fault) is not None
            ]
            ci = [(c.get("detection_probability_ci") or {}).get(fault) for *_, c in p]
            h = series(ax_p, [(x, y) for x, y, _ in p], style, ci)
            if h is not None:
                legend.append(h)
            d = [(xpos(c, mi, fi, len(faults)), _get(c, "median_delay_s", fault)) for c in mcells]
            d = [(x, y) for x, y in d if y is not None]
            series(ax_d, d, {**style, "label": None})
            delays_all += [y for _, y in d]
        grey = _METHOD_GREY[mi % len(_METHOD_GREY)]
        mstyle = {
            "color": grey,
            "ls": ms["ls"],
            "marker": ms["marker"],
            "ms": 6,
            "mfc": ms["mfc"] or grey,
            "label": method.upper(),
        }
        iso = [
            (xpos(c, mi), _get(c, "isolation_accuracy"), c.get("isolation_accuracy_ci"))
            for c in mcells
            if _get(c, "isolation_accuracy") is not None
        ]
        series(ax_i, [(x, y) for x, y, _ in iso], mstyle, [e for *_, e in iso])
        fpr = [
            (xpos(c, mi), c["false_declarations"] / c["runs"])
            for c in mcells
            if c.get("runs") and c.get("false_declarations") is not None
        ]
        series(ax_f, fpr, mstyle)
        series(
            ax_m,
            [
                (xpos(c, mi), _get(c, "mode_accuracy"))
                for c in mcells
                if _get(c, "mode_accuracy") is not None
            ],
            mstyle,
        )
        for ri, (key, colour) in enumerate((("tdr", "C0"), ("far", "C3"), ("fia", "C2"))):
            pts = [(xpos(c, mi, ri, 3), _get(c, key)) for c in mcells if _get(c, key) is not None]
            rstyle = {
                **mstyle,
                "color": colour,
                "mfc": ms["mfc"] or colour,
                "label": f"{key.upper()} / {method.upper()}",
            }
            series(ax_r, pts, rstyle)
        for ff in (c for c in fault_free if c["method"] == method):
            kw = {"color": grey, "ls": ":", "lw": 1.2}
            if ff.get("runs") and ff.get("false_declarations") is not None:
                ax_f.axhline(
                    ff["false_declarations"] / ff["runs"],
                    **kw,
                    label=f"{method.upper()} fault-free runs",
                )
            if _get(ff, "mode_accuracy") is not None:
                ax_m.axhline(
                    _get(ff, "mode_accuracy"), **kw, label=f"{method.upper()} fault-free runs"
                )
            if _get(ff, "far") is not None:
                ax_r.axhline(
                    _get(ff, "far"),
                    **{**kw, "color": "C3"},
                    label=f"FAR / {method.upper()} fault-free",
                )

    panels = (
        (ax_p, "detection probability", "Detection probability (per fault)"),
        (ax_d, "median detection delay (s)", "Median detection delay (per fault)"),
        (ax_i, "isolation accuracy", "Isolation accuracy (first new declaration)"),
        (ax_f, "false declarations per run", "False declarations per run"),
        (ax_m, "mode accuracy", "Mode accuracy (samples)"),
        (ax_r, "rate", "TDR, FAR, FIA (per sample)"),
    )
    for ax, ylabel, name in panels:
        ax.set_ylabel(ylabel)
        ax.set_title(name, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        if single:
            ax.set_xticks(range(len(methods)), [m.upper() for m in methods])
            ax.set_xlim(-0.6, len(methods) - 0.4)
            ax.set_xlabel(f"method (fault magnitude {mags[0]:g})" if mags else "method")
        else:
            ax.set_xlabel("fault magnitude")
    for ax in (ax_p, ax_i, ax_m, ax_r):
        ax.set_ylim(-0.03, 1.03)
    top = max([1.0] + [float(v) for ln in ax_f.get_lines() for v in np.atleast_1d(ln.get_ydata())])
    # All zero: a 0..1 axis, not a 1e-17 one; the top band is left to the legend.
    ax_f.set_ylim(-0.03 * top, 1.45 * top)
    pos = [d for d in delays_all if d > 0]
    if pos and len(pos) == len(delays_all) and max(pos) / min(pos) > 50:
        ax_d.set_yscale("log")
    if legend:
        ax_p.legend(legend, [h.get_label() for h in legend], fontsize=7)
    for ax in (ax_i, ax_f, ax_m, ax_r):
        if ax.get_legend_handles_labels()[0]:
            kw = {"loc": "upper center", "ncols": 2} if ax is ax_f else {}
            ax.legend(fontsize=7, **kw)
    fig.suptitle(title if title is not None else "Monte Carlo sweep over fault magnitude")
    return fig


def plot_confusion(
    matrix: np.ndarray,
    row_labels: Sequence[str],
    col_labels: Sequence[str],
    *,
    title: str | None = None,
    normalise_rows: bool = True,
) -> Figure:
    """Plot a confusion matrix (true fault x declared fault) as an annotated heat map.

    Args:
        matrix: Counts (or rates), shape (R, C); rows are true faults, columns declared.
        row_labels: The R true-fault names.
        col_labels: The C declared-fault names.
        title: Figure title; a default is used when None.
        normalise_rows: Colour each cell by its share of its row (written under the
            count), so that a large row (the fault-free periods) does not wash out the
            others; ``False`` colours by the raw values.

    Returns:
        The figure (heat map plus colour bar).
    """
    return plot_confusion_grid(
        [("", matrix)], row_labels, col_labels, title=title, normalise_rows=normalise_rows
    )


def plot_confusion_grid(
    panels: Sequence[tuple[str, np.ndarray]],
    row_labels: Sequence[str],
    col_labels: Sequence[str],
    *,
    title: str | None = None,
    normalise_rows: bool = True,
) -> Figure:
    """Several confusion matrices side by side (e.g. one per fault magnitude).

    Args:
        panels: ``(panel title, matrix)`` pairs, every matrix of shape (R, C).
        row_labels: The R true-fault names.
        col_labels: The C declared-fault names.
        title: Figure title; a default is used when None.
        normalise_rows: See :func:`plot_confusion`.

    Returns:
        The figure (one heat map per panel, one colour bar).
    """
    mats = [np.asarray(m) for _, m in panels]
    for m in mats:
        if m.ndim != 2:
            raise ValueError(f"matrix must be 2-D, got shape {m.shape}")
        if len(row_labels) != m.shape[0] or len(col_labels) != m.shape[1]:
            raise ValueError(
                f"{len(row_labels)} x {len(col_labels)} labels for a {m.shape[0]} x "
                f"{m.shape[1]} matrix"
            )
    r, c = mats[0].shape if mats else (len(row_labels), len(col_labels))
    n = max(len(mats), 1)
    ncols = min(n, 3)  # at most three panels a row: the figure stays readable
    nrows = -(-n // ncols)
    fig = Figure(
        figsize=(1.8 + ncols * (1.2 + 1.0 * c), nrows * (0.9 + 0.7 * r) + 1.0),
        layout="constrained",
    )
    grid = fig.subplots(nrows, ncols, squeeze=False)
    axes = list(grid.reshape(-1))
    for ax in axes[n:]:
        ax.remove()
    axes = axes[:n]
    first_col = {id(row[0]) for row in grid}
    im = None
    for ax, (name, _), values in zip(axes, panels, mats, strict=False):
        im = _draw_confusion(ax, values.astype(float), normalise_rows)
        ax.set_xticks(range(c), list(col_labels), rotation=30, ha="right")
        ax.set_yticks(range(r), list(row_labels) if id(ax) in first_col else [""] * r)
        ax.set_xlabel("declared fault")
        if id(ax) in first_col:
            ax.set_ylabel("true fault")
        if name:
            ax.set_title(name, fontsize=10)
    if im is not None:
        label = "share of the row" if normalise_rows else "count"
        fig.colorbar(im, ax=list(axes), shrink=0.9, label=label)
    fig.suptitle(title if title is not None else "Confusion matrix")
    return fig


def _draw_confusion(ax, values: np.ndarray, normalise_rows: bool):
    r, c = values.shape
    if normalise_rows:
        sums = np.nansum(values, axis=1, keepdims=True)
        colours = np.divide(values, sums, out=np.zeros_like(values), where=sums > 0)
        im = ax.imshow(colours, cmap="Blues", vmin=0.0, vmax=1.0, aspect="auto")
    else:
        colours = values
        im = ax.imshow(values, cmap="Blues", vmin=0.0, aspect="auto")
    finite = colours[np.isfinite(colours)]
    vmax = float(finite.max()) if finite.size and not normalise_rows else 1.0
    integral = np.all(np.isfinite(values)) and np.allclose(values, np.round(values))
    for i in range(r):
        for j in range(c):
            v = values[i, j]
            dark = vmax > 0 and colours[i, j] > 0.5 * vmax
            colour = "white" if dark else "black"
            text = f"{int(round(v))}" if integral else f"{v:.3g}"
            dy = -0.12 if normalise_rows else 0.0
            ax.text(j, i + dy, text, ha="center", va="center", color=colour, fontsize=10)
            if normalise_rows:
                share = f"{100 * colours[i, j]:.0f} %" if values[i].sum() > 0 else "-"
                ax.text(j, i + 0.22, share, ha="center", va="center", color=colour, fontsize=7)
    return im


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
