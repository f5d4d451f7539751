"""Figures of one diagnosis run (this and ``plots_sweep`` are the only users of matplotlib).

Every function takes plain NumPy arrays (or array-likes) and returns a
:class:`matplotlib.figure.Figure` built with the object API. :mod:`matplotlib.pyplot` is
never imported, so no backend is selected and no global figure registry is touched:
figures are garbage-collected like any other object. Save them with :func:`save_figure`.

Long runs hold 1e6 samples (100 s at T = 1e-4 s, design notes section 1). Curves are
decimated for drawing by :func:`_decimate`: a min/max envelope per bucket for continuous
signals (peaks and spikes survive) and plain striding for integer mode codes. Summary
numbers printed on figures (e.g. the recognition rate) are always computed on the full
arrays.

References:
    Sun, Wang & Lin, "Multi-Fault Diagnosis Approach Based on Updated Interacting Multiple
    Model for Aviation Hydraulic Actuator", Information 2020, 11, 410. Figure 4 (model
    count), Figures 6 and 8 (mode probabilities), Figures 7 and 9 (mode recognition).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

__all__ = [
    "draw_mode_probabilities",
    "fault_set_name",
    "plot_mode_probabilities",
    "plot_mode_recognition",
    "plot_model_count",
    "plot_states",
    "save_figure",
]

_MAX_POINTS = 20000
_DPI = 120
_CYCLE = [f"C{i}" for i in range(10)]


# --------------------------------------------------------------------------- helpers


def _is_integer_like(a: np.ndarray) -> bool:
    return np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.bool_)


def _decimate(
    t: np.ndarray, *ys: np.ndarray, max_points: int = _MAX_POINTS
) -> tuple[np.ndarray, ...]:
    """Reduce a time series to at most ``max_points`` samples for drawing.

    If ``len(t) <= max_points`` the inputs are returned unchanged (exact). Otherwise:

    * if every ``y`` has an integer or boolean dtype (mode codes), the samples are simply
      strided: ``t[::s], y[::s]`` with ``s = ceil(N / max_points)``;
    * else the samples are cut into ``max_points // 2`` buckets of equal length and each
      bucket contributes two samples, at the bucket's first and last time stamps. For a
      floating-point ``y`` they hold the bucket's minimum and maximum (column by column
      for 2-D ``y``), ordered as they occur, so that the drawn line covers the full
      envelope of the signal and every extreme value survives. An integer ``y`` given
      together with floating-point ones takes its values at those two time stamps.

    Args:
        t: Time stamps, shape (N,).
        *ys: Arrays sharing the leading axis with ``t``, shape (N,) or (N, M).
        max_points: Upper bound on the number of returned samples (at least 2).

    Returns:
        ``(t_dec, *ys_dec)``, all with the same leading length ``<= max_points``.

    Raises:
        ValueError: If an array's leading length differs from ``len(t)`` or
            ``max_points < 2``.
    """
    t = np.asarray(t)
    ys = tuple(np.asarray(y) for y in ys)
    n = t.shape[0]
    for y in ys:
        if y.shape[:1] != (n,):
            raise ValueError(f"leading length {y.shape[:1]} does not match len(t) = {n}")
    if max_points < 2:
        raise ValueError(f"max_points must be at least 2, got {max_points}")
    if n <= max_points:
        return (t, *ys)

    if all(_is_integer_like(y) for y in ys):
        stride = math.ceil(n / max_points)
        return (t[::stride], *(y[::stride] for y in ys))

    # Envelope: nb buckets of `size` samples (the last one padded by repeating its
    # final sample, which changes neither its minimum nor its maximum).
    size = math.ceil(n / (max_points // 2))
    nb = math.ceil(n / size)
    starts = np.arange(nb) * size
    ends = np.minimum(starts + size, n) - 1
    t_out = np.stack([t[starts], t[ends]], axis=1).reshape(-1)

    out = [t_out]
    pad = nb * size - n
    for y in ys:
        if _is_integer_like(y):
            out.append(np.stack([y[starts], y[ends]], axis=1).reshape(-1, *y.shape[1:]))
            continue
        yp = np.concatenate([y, np.repeat(y[-1:], pad, axis=0)], axis=0) if pad else y
        yb = yp.reshape(nb, size, *y.shape[1:])
        i_min = np.argmin(yb, axis=1)
        i_max = np.argmax(yb, axis=1)
        v_min = np.take_along_axis(yb, i_min[:, None], axis=1)[:, 0]
        v_max = np.take_along_axis(yb, i_max[:, None], axis=1)[:, 0]
        min_first = i_min <= i_max
        first = np.where(min_first, v_min, v_max)
        second = np.where(min_first, v_max, v_min)
        out.append(np.stack([first, second], axis=1).reshape(-1, *y.shape[1:]))
    return tuple(out)


def _band(t: np.ndarray, y: np.ndarray, buckets: int) -> tuple[np.ndarray, ...]:
    """``(t_mid, lo, hi, rms)``: min/max envelope and RMS of ``y`` over time buckets.

    With fewer samples than buckets, ``lo = hi = y`` and ``rms = |y|`` (exact).
    """
    t, y = np.asarray(t), np.asarray(y, float)
    n = t.shape[0]
    if n <= buckets:
        return t, y, y, np.abs(y)
    size = math.ceil(n / buckets)
    nb = math.ceil(n / size)
    yp = np.concatenate([y, np.repeat(y[-1:], nb * size - n)]).reshape(nb, size)
    mid = np.minimum(np.arange(nb) * size + size // 2, n - 1)
    rms = np.sqrt(np.mean(yp * yp, axis=1))
    return t[mid], yp.min(axis=1), yp.max(axis=1), rms


def fault_set_name(code: int, fault_names: Sequence[str]) -> str:
    """Name the fault set encoded by a bitmask.

    Args:
        code: Fault-set bitmask; bit ``j`` set means fault ``j`` is present. A negative
            code means "undetermined".
        fault_names: ``fault_names[j]`` names bit ``j``.

    Returns:
        ``"fault-free"`` for 0, otherwise the present faults joined by ``" + "`` in bit
        order (e.g. ``"valve_wear + leakage"``); bits without a name are called
        ``"fault<j>"``.
    """
    code = int(code)
    if code < 0:
        return "undetermined"
    if code == 0:
        return "fault-free"
    names = []
    j = 0
    while code >> j:
        if (code >> j) & 1:
            names.append(fault_names[j] if j < len(fault_names) else f"fault{j}")
        j += 1
    return " + ".join(names)


def _as_2d(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    return a[:, None] if a.ndim == 1 else a


def _plain_log_ticks(ax) -> None:
    """Label a log y axis at 1, 2, 5 x 10^k with plain numbers (no minor labels)."""
    ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_major_formatter(ScalarFormatter())
    ax.yaxis.set_minor_formatter(NullFormatter())


def _check_t(t: np.ndarray, *arrays: np.ndarray) -> np.ndarray:
    t = np.asarray(t)
    if t.ndim != 1:
        raise ValueError(f"t must be 1-D, got shape {t.shape}")
    for a in arrays:
        if np.shape(a)[:1] != t.shape:
            raise ValueError(f"array of shape {np.shape(a)} does not match t of shape {t.shape}")
    return t


# --------------------------------------------------------------------------- figures


def plot_mode_probabilities(
    t: np.ndarray,
    mode_probs: np.ndarray,
    model_labels: Sequence[str],
    *,
    events: Sequence[tuple[float, str]] = (),
    declarations: Sequence[tuple[float, str]] = (),
    title: str | None = None,
    max_points: int = _MAX_POINTS,
) -> Figure:
    """Plot the mode probability of every model in the bank against time.

    Reproduces paper Figures 6 (simulation 1) and 8 (simulation 2): one line per model,
    with y in [0, 1]. True fault onsets are drawn as dashed vertical lines and fault
    declarations of the estimator as solid vertical lines topped by a triangle; both
    take the colour of the model whose label equals the fault name, or black.

    Args:
        t: Time stamps in seconds, shape (N,).
        mode_probs: Mode probabilities, shape (N, M).
        model_labels: Name of each of the M models (legend entries).
        events: True fault onsets as ``(time, fault_name)`` pairs.
        declarations: Declarations as ``(time, fault_name)`` pairs.
        title: Figure title; a default is used when None.
        max_points: Most samples drawn per curve (see :func:`_decimate`); rendering
            time grows linearly with it (about 1 s per 5000 points of a noisy curve).

    Returns:
        The figure (one axes).
    """
    mode_probs = _as_2d(mode_probs)
    t = _check_t(t, mode_probs)
    m = mode_probs.shape[1]
    if len(model_labels) != m:
        raise ValueError(f"{len(model_labels)} model labels for {m} models")
    fig = Figure(figsize=(9.0, 4.2), layout="constrained")
    ax = fig.add_subplot()
    draw_mode_probabilities(
        ax, t, mode_probs, model_labels, events=events, declarations=declarations,
        max_points=max_points,
    )  # fmt: skip
    ax.set_title(title if title is not None else "Mode probabilities (cf. paper Figs. 6/8)")
    return fig


def draw_mode_probabilities(
    ax, t, mode_probs, model_labels, *, events=(), declarations=(), max_points=_MAX_POINTS
) -> None:
    """Draw :func:`plot_mode_probabilities` into ``ax`` (also used by the zoom panels).

    Onsets are dashed vertical lines, declarations solid lines topped by a triangle, in
    the colour of the model named after the fault (or black).  Markers outside the time
    range of ``t`` are left out.
    """
    colour = {label: _CYCLE[j % len(_CYCLE)] for j, label in enumerate(model_labels)}
    for label, c in list(colour.items()):  # a UIMM hypothesis "D + f" lends f its colour
        if label.startswith("D + "):
            colour.setdefault(label[4:], c)
    td, pd = _decimate(t, np.asarray(mode_probs, dtype=float), max_points=max_points)
    for j, label in enumerate(model_labels):
        ax.plot(td, pd[:, j], color=colour[label], lw=1.1, label=str(label))

    # Markers far outside the data (a short measured file against the scenario's onsets)
    # would stretch the axis, or overflow the text rasteriser: draw only those in range.
    start = float(t[0]) if len(t) else 0.0
    end = float(t[-1]) if len(t) else 0.0
    events = [(time, name) for time, name in events if start <= time <= end]
    declarations = [(time, name) for time, name in declarations if start <= time <= end]
    for time, name in events:
        ax.axvline(time, color=colour.get(name, "k"), ls="--", lw=1.2, alpha=0.9)
        ax.annotate(
            f"{name} onset",
            (time, 0.5),
            xycoords=("data", "axes fraction"),
            xytext=(-2, 0),
            textcoords="offset points",
            rotation=90,
            ha="right",
            va="center",
            fontsize=8,
            color=colour.get(name, "k"),
            bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "none", "alpha": 0.8},
        )
    for time, name in declarations:
        c = colour.get(name, "k")
        ax.axvline(time, color=c, ls="-", lw=1.6, alpha=0.8)
        ax.plot([time], [1.04], marker="v", ms=8, color=c, clip_on=False)

    handles, labels = ax.get_legend_handles_labels()
    if events:
        handles.append(Line2D([], [], color="k", ls="--", lw=1.2))
        labels.append("true fault onset")
    if declarations:
        handles.append(Line2D([], [], color="k", ls="-", lw=1.6, marker="v", ms=6))
        labels.append("declaration")
    ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    ax.set_ylim(-0.02, 1.08)
    if len(t) > 1:  # one sample: matplotlib widens the axis itself
        ax.set_xlim(t[0], t[-1])
    ax.set_xlabel("time (s)")
    ax.set_ylabel("mode probability")
    ax.grid(True, alpha=0.3)


def plot_mode_recognition(
    t: np.ndarray,
    recognised: np.ndarray,
    truth: np.ndarray,
    fault_names: Sequence[str],
    *,
    title: str | None = None,
    max_points: int = _MAX_POINTS,
) -> Figure:
    """Plot the recognised fault set against the true one on a categorical axis.

    Reproduces paper Figures 7 (simulation 1) and 9 (simulation 2). The y axis lists only
    the fault sets that occur in either array, ordered by number of faults and then by
    code, labelled by :func:`fault_set_name`. The truth is a wide grey step line through
    its exact change points; the recognised set is drawn as dots (strided when long) and
    the samples where it disagrees with the truth as red crosses, picked from the full
    arrays (so isolated misrecognitions stay visible; strided only if more than
    ``max_points``). The fraction of agreeing samples, over all N samples, is written in
    the axes.

    Args:
        t: Time stamps in seconds, shape (N,).
        recognised: Recognised fault-set bitmasks, int array of shape (N,).
        truth: True fault-set bitmasks, int array of shape (N,).
        fault_names: ``fault_names[j]`` names bit ``j``.
        title: Figure title; a default is used when None.
        max_points: Most samples drawn per curve (see :func:`_decimate`); rendering
            time grows linearly with it (about 1 s per 5000 points of a noisy curve).

    Returns:
        The figure (one axes).
    """
    recognised = np.asarray(recognised).astype(np.int64)
    truth = np.asarray(truth).astype(np.int64)
    t = _check_t(t, recognised, truth)

    codes = sorted(
        set(np.unique(recognised).tolist()) | set(np.unique(truth).tolist()),
        key=lambda c: (c < 0, int(c).bit_count() if c >= 0 else 0, c),
    )
    keys = np.array(codes, dtype=np.int64)
    rec_cat = _map_codes(recognised, keys)
    truth_cat = _map_codes(truth, keys)
    agree = recognised == truth
    rate = float(agree.mean()) if agree.size else float("nan")

    fig = Figure(figsize=(9.0, 1.6 + 0.45 * len(codes)), layout="constrained")
    ax = fig.add_subplot()

    # Truth: exact step line through its change points only.
    if len(t):
        change = np.flatnonzero(np.diff(truth_cat)) + 1
        idx = np.concatenate([[0], change])
        ts = np.append(t[idx], t[-1])
        ys = np.append(truth_cat[idx], truth_cat[-1])
        ax.step(ts, ys, where="post", color="0.55", lw=7.0, alpha=0.4, label="true mode", zorder=2)

    td, rd = _decimate(t, rec_cat, max_points=max_points)
    ax.plot(td, rd, ls="none", marker=".", ms=3, color="C0", label="recognised", zorder=3)
    bad = np.flatnonzero(~agree)
    if bad.size:
        bad = bad[:: math.ceil(bad.size / max_points)]
        ax.plot(
            t[bad],
            rec_cat[bad],
            ls="none",
            marker="x",
            ms=4,
            color="C3",
            label="misrecognised",
            zorder=4,
        )

    ax.set_yticks(range(len(codes)), [fault_set_name(c, fault_names) for c in codes])
    ax.set_ylim(-0.6, len(codes) - 0.4)
    if len(t) > 1:  # one sample: matplotlib widens the axis itself
        ax.set_xlim(t[0], t[-1])
    ax.set_xlabel("time (s)")
    ax.set_ylabel("fault set")
    ax.grid(True, axis="x", alpha=0.3)
    ax.text(
        0.99,
        0.03,
        f"agreement: {100 * rate:.2f} % of {agree.size} samples",
        transform=ax.transAxes,
        ha="right",
        va="bottom",
        fontsize=9,
        bbox={"boxstyle": "round", "fc": "white", "ec": "0.7", "alpha": 0.9},
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    ax.set_title(title if title is not None else "Mode recognition (cf. paper Figs. 7/9)")
    return fig


def _map_codes(a: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Return, for every entry of ``a``, its position in ``keys`` (which must contain it)."""
    order = np.argsort(keys, kind="stable")
    pos = np.searchsorted(keys[order], a)
    return order[pos]


def plot_states(
    t: np.ndarray,
    x_true: np.ndarray,
    x_est: np.ndarray,
    state_names: Sequence[str],
    *,
    units: Sequence[str] | None = None,
    residuals: bool = True,
    title: str | None = None,
    max_points: int = _MAX_POINTS,
) -> Figure:
    """Plot true and estimated states, one panel per state.

    The paper shows no state figure; this one checks the combined estimate of the bank
    (paper eq. 30) against the simulated truth. Each state gets a main panel and, when
    ``residuals`` is true, a small panel below it with the estimation error
    ``x_est - x_true`` drawn as its min/max envelope and its ±RMS per time bucket (1000
    buckets: a band and two lines, not a zig-zag through 1e6 points). Where ``x_true``
    is all NaN (measured data), only the estimates are
    drawn, without error panels.

    Args:
        t: Time stamps in seconds, shape (N,).
        x_true: True states, shape (N, S).
        x_est: Estimated states, shape (N, S).
        state_names: Name of each of the S states.
        units: Unit of each state (e.g. ``["m", "m/s", "Pa"]``), or None.
        residuals: Whether to add an error panel under each state.
        title: Figure title; a default is used when None.
        max_points: Most samples drawn per curve (see :func:`_decimate`); rendering
            time grows linearly with it (about 1 s per 5000 points of a noisy curve).

    Returns:
        The figure (S or 2 S axes sharing the time axis).
    """
    x_true = _as_2d(np.asarray(x_true, dtype=float))
    x_est = _as_2d(np.asarray(x_est, dtype=float))
    t = _check_t(t, x_true, x_est)
    if x_true.shape != x_est.shape:
        raise ValueError(f"x_true {x_true.shape} and x_est {x_est.shape} differ in shape")
    s = x_true.shape[1]
    if len(state_names) != s:
        raise ValueError(f"{len(state_names)} state names for {s} states")
    if units is not None and len(units) != s:
        raise ValueError(f"{len(units)} units for {s} states")

    have_truth = bool(np.isfinite(x_true).any())  # measured data: no true states
    residuals = residuals and have_truth
    td, xt, xe = _decimate(t, x_true, x_est, max_points=max_points)
    rows_per_state = 2 if residuals else 1
    ratios = [3, 1] * s if residuals else [1] * s
    fig = Figure(figsize=(9.0, (2.6 if residuals else 2.0) * s + 0.6), layout="constrained")
    gs = fig.add_gridspec(rows_per_state * s, 1, height_ratios=ratios)
    first = None
    axes = []
    for k in range(s):
        unit = f" ({units[k]})" if units is not None and units[k] else ""
        ax = fig.add_subplot(gs[rows_per_state * k], sharex=first)
        first = first or ax
        if have_truth:
            ax.plot(td, xt[:, k], color="k", lw=1.4, label="true")
        ax.plot(td, xe[:, k], color="C1", lw=1.0, ls="--" if have_truth else "-", label="estimate")
        ax.set_ylabel(f"{state_names[k]}{unit}")
        ax.grid(True, alpha=0.3)
        if k == 0:
            ax.legend(loc="upper right", fontsize=9)
        axes.append(ax)
        if residuals:
            axr = fig.add_subplot(gs[rows_per_state * k + 1], sharex=first)
            tb, lo, hi, rms = _band(t, x_est[:, k] - x_true[:, k], 1000)
            axr.fill_between(tb, lo, hi, color="C3", alpha=0.25, lw=0, label="min/max")
            axr.plot(tb, rms, color="C3", lw=0.9, label="RMS")
            axr.plot(tb, -rms, color="C3", lw=0.9)
            axr.axhline(0.0, color="0.3", lw=0.6)
            if k == 0:
                axr.legend(loc="upper right", fontsize=7, ncols=2)
            axr.set_ylabel(f"error{unit}", fontsize=8)
            axr.tick_params(labelsize=8)
            axr.grid(True, alpha=0.3)
            axes.append(axr)
    for ax in axes[:-1]:
        ax.tick_params(labelbottom=False)
    axes[-1].set_xlabel("time (s)")
    if len(t) > 1:
        axes[-1].set_xlim(t[0], t[-1])
    fig.suptitle(title if title is not None else "True and estimated states")
    return fig


def plot_model_count(
    max_faults: int = 10,
    *,
    measured: Mapping[str, Sequence[float]] | None = None,
    title: str | None = None,
) -> Figure:
    """Plot the number of models needed by IMM and UIMM against the number of faults.

    Reproduces paper Figure 4: a combinatorial IMM needs one model per fault set, 2**F,
    whereas the UIMM keeps F + 1 (paper section 3.3). With ``measured`` a second panel
    shows the measured cost per filter step.

    Args:
        max_faults: Largest number of faults F; F runs over 1..max_faults.
        measured: Optional timings with keys ``"F"``, ``"imm_us"`` and ``"uimm_us"``
            (equal-length sequences, microseconds per step; NaN where not run).
        title: Optional figure title above the panels.

    Returns:
        The figure (one axes, or two side by side with ``measured``).
    """
    if max_faults < 1:
        raise ValueError(f"max_faults must be at least 1, got {max_faults}")
    f = np.arange(1, max_faults + 1)
    ncols = 2 if measured is not None else 1
    fig = Figure(figsize=(5.0 * ncols + 0.5, 4.0), layout="constrained")
    ax = fig.add_subplot(1, ncols, 1)
    ax.semilogy(f, 2.0**f, "o-", color="C3", label="IMM: $2^F$")
    ax.semilogy(f, f + 1.0, "s-", color="C0", label="UIMM: $F+1$")
    _plain_log_ticks(ax)
    ax.set_xticks(f)
    ax.set_xlabel("number of faults F")
    ax.set_ylabel("number of models")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    ax.set_title("Models required (cf. paper Fig. 4)")

    if measured is not None:
        fm = np.asarray(measured["F"], dtype=float)
        ax2 = fig.add_subplot(1, 2, 2)
        for key, label, style, c in (
            ("imm_us", "IMM", "o-", "C3"),
            ("uimm_us", "UIMM", "s-", "C0"),
        ):
            if key not in measured:
                continue
            v = np.asarray(measured[key], dtype=float)
            if v.shape != fm.shape:
                raise ValueError(f"measured[{key!r}] has shape {v.shape}, F has {fm.shape}")
            ok = np.isfinite(v) & (v > 0)
            if ok.any():
                ax2.plot(fm[ok], v[ok], style, color=c, label=label)
        ax2.set_yscale("log")
        _plain_log_ticks(ax2)
        ax2.set_xticks(np.unique(fm[np.isfinite(fm)]))
        ax2.set_xlabel("number of faults F")
        ax2.set_ylabel("time per step (µs)")
        ax2.grid(True, which="both", alpha=0.3)
        if ax2.get_legend_handles_labels()[0]:
            ax2.legend()
        ax2.set_title("Measured cost per step")
    if title is not None:
        fig.suptitle(title)
    return fig


def save_figure(fig: Figure, path: str | os.PathLike) -> Path:
    """Save a figure at 120 dpi, creating the parent directories.

    The format follows the file suffix (``.png``, ``.pdf``, ``.svg``...). Nothing is
    closed: figures built here are not registered with pyplot, so dropping the last
    reference frees them.

    Args:
        fig: The figure to save.
        path: Destination file.

    Returns:
        The destination as a :class:`pathlib.Path`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=_DPI)
    return path
