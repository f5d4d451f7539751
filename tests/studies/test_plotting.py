"""studies.plots and plots_sweep: every figure builds and saves; decimation keeps extremes."""

from __future__ import annotations

import importlib
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from matplotlib.figure import Figure

_MODULES = ("uimm_jax.studies.plots", "uimm_jax.studies.plots_sweep")

# The figure modules, imported by name; the same lines run in the subprocess of
# test_no_pyplot_import.
_LOADER = textwrap.dedent(
    f"""
    import importlib, sys
    plots, plots_sweep = (importlib.import_module(m) for m in {_MODULES!r})
    """
)

plots, plots_sweep = (importlib.import_module(m) for m in _MODULES)

FAULTS = ["valve_wear", "leakage", "air_in_oil"]


def _saved(fig, tmp_path, name):
    assert isinstance(fig, Figure)
    out = plots.save_figure(fig, tmp_path / "sub" / "dir" / f"{name}.png")
    assert out.exists()
    data = out.read_bytes()
    assert len(data) > 1000
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return out


def _sim1(n=3000, seed=0):
    """A synthetic sim-1 like run: fault-free, valve wear at 30 s, + leakage at 60 s."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 100.0, n)
    truth = np.where(t < 30, 0, np.where(t < 60, 0b001, 0b011)).astype(np.int32)
    recognised = truth.copy()
    flip = rng.random(n) < 0.02
    recognised[flip] = rng.choice([0, 1, 3, 5], size=flip.sum())
    models = ["fault-free", "valve_wear", "leakage", "air_in_oil"]
    active = np.zeros((n, 4))
    active[t < 30, 0] = 5
    active[(t >= 30) & (t < 60), 1] = 5
    active[t >= 60, 2] = 5
    logits = rng.normal(size=(n, 4)) + active
    probs = np.exp(logits - logits.max(axis=1, keepdims=True))
    probs /= probs.sum(axis=1, keepdims=True)
    return t, truth, recognised, probs, models


# ------------------------------------------------------------------------ _decimate


def test_decimate_exact_when_short():
    t = np.arange(100.0)
    y = np.sin(t)
    codes = np.arange(100) % 3
    td, yd, cd = plots._decimate(t, y, codes, max_points=100)
    np.testing.assert_array_equal(td, t)
    np.testing.assert_array_equal(yd, y)
    np.testing.assert_array_equal(cd, codes)


@pytest.mark.parametrize("n", [20001, 100_003, 1_000_000])
def test_decimate_envelope_keeps_extremes(n):
    rng = np.random.default_rng(n)
    t = np.arange(n) * 1e-4
    y = rng.normal(size=n)
    y[n // 3] = 50.0  # isolated spikes that striding would almost surely miss
    y[2 * n // 3 + 1] = -40.0
    y2 = np.stack([np.cos(t), rng.normal(size=n)], axis=1)
    max_points = 20000
    td, yd, y2d = plots._decimate(t, y, y2, max_points=max_points)
    assert len(td) <= max_points
    assert len(td) >= max_points // 2  # not wastefully coarse
    assert yd.shape == td.shape and y2d.shape == (len(td), 2)
    assert yd.max() == y.max() == 50.0
    assert yd.min() == y.min() == -40.0
    np.testing.assert_array_equal(y2d.max(axis=0), y2.max(axis=0))
    np.testing.assert_array_equal(y2d.min(axis=0), y2.min(axis=0))
    assert np.all(np.diff(td) >= 0)
    assert td[0] == t[0] and td[-1] == t[-1]


def test_decimate_keeps_min_and_max_of_every_bucket():
    rng = np.random.default_rng(1)
    n, max_points = 10_000, 100
    t = np.arange(n, dtype=float)
    y = rng.normal(size=n)
    td, yd = plots._decimate(t, y, max_points=max_points)
    assert len(td) <= max_points
    # Each decimated pair (first, last time of a bucket) brackets the bucket's samples.
    for k in range(0, len(td), 2):
        lo, hi = int(td[k]), int(td[k + 1])
        bucket = y[lo : hi + 1]
        assert {yd[k], yd[k + 1]} == {bucket.min(), bucket.max()}


def test_decimate_strides_integer_codes():
    n = 1_000_000
    t = np.arange(n) * 1e-4
    codes = (np.arange(n) // 300_000).astype(np.int32)
    td, cd = plots._decimate(t, codes, max_points=20000)
    assert len(td) <= 20000
    assert cd.dtype == codes.dtype
    assert set(np.unique(cd)) <= set(np.unique(codes))
    np.testing.assert_array_equal(cd, codes[np.searchsorted(t, td)])  # exact samples


def test_decimate_rejects_bad_shapes():
    with pytest.raises(ValueError):
        plots._decimate(np.arange(10.0), np.arange(9.0))


# ------------------------------------------------------------------------ figures


def test_fault_set_name():
    assert plots.fault_set_name(0, FAULTS) == "fault-free"
    assert plots.fault_set_name(1, FAULTS) == "valve_wear"
    assert plots.fault_set_name(0b011, FAULTS) == "valve_wear + leakage"
    assert plots.fault_set_name(0b101, FAULTS) == "valve_wear + air_in_oil"
    assert plots.fault_set_name(0b1000, FAULTS) == "fault3"


def test_plot_mode_probabilities(tmp_path):
    t, _, _, probs, models = _sim1()
    fig = plots.plot_mode_probabilities(
        t,
        probs,
        models,
        events=[(30.0, "valve_wear"), (60.0, "leakage")],
        declarations=[(30.4, "valve_wear"), (61.0, "leakage")],
        title="sim 1",
    )
    _saved(fig, tmp_path, "mode_probs")
    (ax,) = fig.axes
    assert ax.get_ylim()[0] <= 0.0 and ax.get_ylim()[1] >= 1.0
    assert [text.get_text() for text in ax.get_legend().get_texts()][:4] == models


def test_plot_mode_probabilities_long_run_is_decimated(tmp_path):
    n = 1_000_000
    t = np.arange(n) * 1e-4
    p = np.full((n, 2), 0.5)
    p[n // 2, 0] = 1.0
    fig = plots.plot_mode_probabilities(t, p, ["a", "b"])
    line = fig.axes[0].get_lines()[0]
    assert len(line.get_xdata()) <= 20000
    assert np.max(line.get_ydata()) == 1.0
    _saved(fig, tmp_path, "mode_probs_long")
    fig = plots.plot_mode_probabilities(t, p, ["a", "b"], max_points=2000)
    line = fig.axes[0].get_lines()[0]
    assert len(line.get_xdata()) <= 2000 and np.max(line.get_ydata()) == 1.0


def test_plot_mode_recognition(tmp_path):
    t, truth, recognised, _, _ = _sim1()
    fig = plots.plot_mode_recognition(t, recognised, truth, FAULTS)
    _saved(fig, tmp_path, "recognition")
    ax = fig.axes[0]
    labels = [tick.get_text() for tick in ax.get_yticklabels()]
    assert labels == ["fault-free", "valve_wear", "valve_wear + leakage", "valve_wear + air_in_oil"]
    rate = np.mean(recognised == truth)
    texts = " ".join(text.get_text() for text in ax.texts)
    assert f"{100 * rate:.2f} %" in texts


def test_plot_mode_recognition_perfect(tmp_path):
    t = np.linspace(0, 1, 50)
    truth = np.zeros(50, dtype=int)
    fig = plots.plot_mode_recognition(t, truth, truth, FAULTS)
    assert "100.00 %" in " ".join(text.get_text() for text in fig.axes[0].texts)
    assert [tick.get_text() for tick in fig.axes[0].get_yticklabels()] == ["fault-free"]
    _saved(fig, tmp_path, "recognition_perfect")


@pytest.mark.parametrize("residuals", [True, False])
def test_plot_states(tmp_path, residuals):
    rng = np.random.default_rng(0)
    t = np.linspace(0, 10, 2000)
    x = np.stack([1e-3 * np.sin(t), 1e-3 * np.cos(t), 1e6 * np.sin(0.3 * t)], axis=1)
    xe = x * (1 + 0.01 * rng.normal(size=x.shape))
    fig = plots.plot_states(
        t, x, xe, ["x_p", "v_p", "p_h"], units=["m", "m/s", "Pa"], residuals=residuals
    )
    assert len(fig.axes) == (6 if residuals else 3)
    _saved(fig, tmp_path, f"states_{residuals}")


def test_plot_model_count(tmp_path):
    fig = plots.plot_model_count()
    (ax,) = fig.axes
    assert ax.get_yscale() == "log"
    imm, uimm = ax.get_lines()[:2]
    np.testing.assert_array_equal(imm.get_ydata(), 2.0 ** np.arange(1, 11))
    np.testing.assert_array_equal(uimm.get_ydata(), np.arange(2, 12))
    _saved(fig, tmp_path, "model_count")

    measured = {
        "F": [1, 2, 3, 4, 6],
        "imm_us": [10.0, 20.0, 45.0, 100.0, float("nan")],
        "uimm_us": [9.0, 12.0, 15.0, 18.0, 25.0],
    }
    fig = plots.plot_model_count(6, measured=measured)
    assert len(fig.axes) == 2 and fig.axes[1].get_yscale() == "log"
    _saved(fig, tmp_path, "model_count_measured")


def test_plot_sweep(tmp_path):
    cells = []
    for method in ["uimm", "imm"]:
        for mag in [0.25, 0.5, 1.0]:
            cells.append(
                {
                    "method": method,
                    "magnitude": mag,
                    "detection_probability": {"valve_wear": mag, "leakage": mag**2},
                    "detection_probability_ci": {
                        "valve_wear": [max(0.0, mag - 0.1), min(1.0, mag + 0.1)],
                        "leakage": [mag**2 * 0.8, min(1.0, mag**2 * 1.2)],
                    },
                    "median_delay_s": {"valve_wear": 1.0 / mag, "leakage": None},
                }
            )
    cells.append(  # a cell without CIs
        {
            "method": "bank",
            "magnitude": 0.5,
            "detection_probability": {"valve_wear": 0.3},
            "median_delay_s": {"valve_wear": None},
        }
    )
    for c in cells:  # the per-method metrics of results.json cells
        c.update(runs=10, false_declarations=1, isolation_accuracy=0.9, mode_accuracy=0.95)
        c.update(tdr=0.97, far=0.001, fia=0.93, isolation_accuracy_ci=[0.8, 0.95])
    fault_free = [{"method": "uimm", "runs": 10, "false_declarations": 0, "mode_accuracy": 1.0}]
    fig = plots_sweep.plot_sweep(cells, fault_free=fault_free, title="sweep")
    assert len(fig.axes) == 6
    titles = " ".join(ax.get_title() for ax in fig.axes)
    for word in ("Detection probability", "Isolation", "False declarations", "Mode accuracy"):
        assert word in titles
    # UIMM and IMM are told apart by marker and fill, and nudged apart on x.
    lines = [ln for ln in fig.axes[0].get_lines() if len(ln.get_xdata()) == 3]
    uimm = next(ln for ln in lines if ln.get_marker() == "o")
    imm = next(ln for ln in lines if ln.get_marker() == "s")
    assert uimm.get_markerfacecolor() != imm.get_markerfacecolor()
    assert not np.allclose(np.asarray(uimm.get_xdata(), float), np.asarray(imm.get_xdata(), float))
    _saved(fig, tmp_path, "sweep")


def test_plot_sweep_false_declarations_legend_covers_no_point(tmp_path):
    """Two false declarations per run below full magnitude (the magnitude sweep): the
    legend of that panel sits above the points, not on them."""
    cells = [
        {"method": m, "magnitude": mag, "detection_probability": {"a": 1.0},
         "runs": 32, "false_declarations": (64 if m == "uimm" else 33) * (mag < 1.0)}
        for m in ("uimm", "imm") for mag in (0.25, 0.5, 0.75, 1.0)
    ]  # fmt: skip
    fault_free = [{"method": m, "runs": 32, "false_declarations": 0} for m in ("uimm", "imm")]
    fig = plots_sweep.plot_sweep(cells, fault_free=fault_free)
    fig.canvas.draw()
    ax = next(a for a in fig.axes if a.get_title().startswith("False declarations"))
    box = ax.get_legend().get_window_extent()
    for line in ax.get_lines():
        if line.get_transform() != ax.transData:  # the fault-free lines span the axes
            continue
        xy = np.column_stack([line.get_xdata(), line.get_ydata()]).astype(float)
        for px, py in ax.transData.transform(xy):
            assert not (box.x0 <= px <= box.x1 and box.y0 <= py <= box.y1), (px, py, box)
    _saved(fig, tmp_path, "sweep_false_legend")


def test_plot_sweep_single_magnitude_is_a_dot_chart(tmp_path):
    cells = [
        {"method": m, "magnitude": 0.5, "detection_probability": {"a": 1.0, "b": 0.5},
         "runs": 4, "false_declarations": 2, "isolation_accuracy": 0.25, "mode_accuracy": 0.3}
        for m in ("uimm", "imm")
    ]  # fmt: skip
    fig = plots_sweep.plot_sweep(cells)
    for ax in fig.axes:
        assert [t.get_text() for t in ax.get_xticklabels()] == ["UIMM", "IMM"]
        assert "magnitude 0.5" in ax.get_xlabel()
    _saved(fig, tmp_path, "sweep_single")


def test_plot_confusion(tmp_path):
    m = np.array([[50, 2, 0], [3, 40, 7], [0, 1, 45]])
    labels = ["none", "valve_wear", "leakage"]
    fig = plots_sweep.plot_confusion(m, labels, labels)
    texts = {text.get_text() for text in fig.axes[0].texts}
    assert {"50", "2", "0", "45"} <= texts
    _saved(fig, tmp_path, "confusion")


def test_confusion_colours_are_row_shares(tmp_path):
    m = np.array([[5000, 2], [3, 7]])  # a large fault-free row
    fig = plots_sweep.plot_confusion(m, ["fault-free", "f"], ["f", "none"])
    colours = fig.axes[0].images[0].get_array()
    np.testing.assert_allclose(colours, m / m.sum(axis=1, keepdims=True))
    texts = {text.get_text() for text in fig.axes[0].texts}
    assert {"5000", "70 %", "30 %"} <= texts
    grid = plots_sweep.plot_confusion_grid(
        [("magnitude 0.5", m), ("magnitude 1", m)], ["a", "b"], ["c", "d"]
    )
    assert len(grid.axes) == 3  # two panels and the colour bar
    _saved(grid, tmp_path, "confusion_grid")


def test_mode_probabilities_detail_zooms_and_declared_sets(tmp_path):
    from uimm_jax.studies import plots_run

    t = (np.arange(100_000) + 1) * 1e-4
    p = np.full((t.size, 3), 0.0)
    p[:, 0] = 1.0
    labels = ["D (no new fault)", "D + a", "D + b"]
    decl = [(3.0391, "a"), (6.0206, "b")]
    fig = plots_run.plot_mode_probabilities_detail(
        t, p, labels, events=[(3.0, "a"), (6.0, "b")], declarations=decl,
        declared_sets=plots_run.declared_set_labels(decl), delays={"a": 0.0391, "b": None},
    )  # fmt: skip
    main, z1, z2 = fig.axes
    assert z1.get_xlim() == pytest.approx((2.5, 3.5), abs=2e-4)
    assert "declared after 39.1 ms" in z1.get_title() and "not declared" in z2.get_title()
    notes = [a.get_text() for a in main.texts]
    assert "D = {a}" in notes and "D = {a, b}" in notes
    assert plots_run.declared_set_labels([(1.0, "a"), (1.0, "b")]) == [(1.0, "D = {a, b}")]
    _saved(fig, tmp_path, "mode_probabilities_detail")


def test_plot_states_measured_data_shows_estimates_only(tmp_path):
    t = np.linspace(0, 1, 500)
    xe = np.stack([np.sin(t), np.cos(t)], axis=1)
    fig = plots.plot_states(t, np.full_like(xe, np.nan), xe, ["x", "v"], units=["m", "m/s"])
    assert len(fig.axes) == 2  # no error panels
    assert [ln.get_label() for ln in fig.axes[0].get_lines()] == ["estimate"]
    assert fig.axes[1].get_ylabel() == "v (m/s)"
    _saved(fig, tmp_path, "states_measured")


def test_plot_states_error_is_an_envelope(tmp_path):
    rng = np.random.default_rng(1)
    t = np.linspace(0, 100, 1_000_000)
    x = np.sin(t)[:, None]
    err = rng.normal(size=x.shape) * 1e-3
    fig = plots.plot_states(t, x, x + err, ["x"], units=["m"])
    ax_err = fig.axes[1]
    (band,) = ax_err.collections
    verts = band.get_paths()[0].vertices
    assert len(verts) < 5000  # 1000 buckets, not 1e6 points
    assert verts[:, 1].max() == pytest.approx(err.max()) and verts[:, 1].min() == pytest.approx(
        err.min()
    )
    assert ax_err.get_ylabel() == "error (m)"


def test_plot_loss_curve(tmp_path):
    k = np.arange(200)
    fig = plots_sweep.plot_loss_curve(100.0 * np.exp(-k / 20) + 0.01)
    assert fig.axes[0].get_yscale() == "log"
    _saved(fig, tmp_path, "loss")
    fig = plots_sweep.plot_loss_curve(
        {"train": np.linspace(2, 1, 50), "val": np.linspace(2.2, 1.3, 50)}
    )
    assert fig.axes[0].get_yscale() == "linear"
    _saved(fig, tmp_path, "loss_dict")


def test_innovation_window_means_equal_a_loop_and_skip_missing_samples():
    """Each window's mean of each output's NIS, NaN (missing) left out, the last window
    partial, a window with nothing observed NaN: against a plain loop."""
    from uimm_jax.studies.plots_innovation import window_means

    rng = np.random.default_rng(0)
    a = rng.chisquare(1, (1037, 2))
    a[rng.random(a.shape) < 0.2] = np.nan
    a[100:200, 1] = np.nan  # window 1 of output 1: nothing observed
    start, got = window_means(a, 100)
    assert start.tolist() == list(range(0, 1037, 100)) and got.shape == (11, 2)
    for w, s0 in enumerate(start):
        for i in range(2):
            block = [v for v in a[s0 : s0 + 100, i] if np.isfinite(v)]
            want = np.mean(block) if block else np.nan
            np.testing.assert_allclose(got[w, i], want, rtol=1e-13, equal_nan=True)
    assert np.isnan(got[1, 1])


def test_plot_innovation_one_panel_per_output(tmp_path):
    """The figure of the innovation check: a panel per output, each with its run mean."""
    from uimm_jax.studies.plots_innovation import plot_innovation

    rng = np.random.default_rng(1)
    t = np.arange(1, 5001) * 1e-3
    ch = rng.chisquare(1, (5000, 3)) * np.array([1.0, 4.0, 1.0])
    ch[::7, 2] = np.nan
    fig = plot_innovation(
        t, ch, ["x_p", "v_p", "p_h"], events=[(2.0, "leak")], declarations=[(2.1, "leak")]
    )
    assert len(fig.axes) == 3
    labels = [ax.get_ylabel().split()[0] for ax in fig.axes]
    assert labels == ["x_p", "v_p", "p_h"]
    texts = [ax.texts[0].get_text() for ax in fig.axes]
    assert texts[1] == f"run mean {np.mean(ch[:, 1]):.3g}"
    assert texts[2] == f"run mean {np.nanmean(ch[:, 2]):.3g}"
    _saved(fig, tmp_path, "innovation")


def test_no_pyplot_import():
    code = _LOADER + textwrap.dedent(
        """
        assert hasattr(plots, "plot_mode_probabilities")
        import numpy as np
        fig = plots.plot_model_count(3)
        fig = plots_sweep.plot_loss_curve(np.linspace(2.0, 1.0, 10))
        print("pyplot" if "matplotlib.pyplot" in sys.modules else "clean")
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert result.stdout.strip().splitlines()[-1] == "clean", result.stderr
