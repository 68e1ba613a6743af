"""Figures that tell the truth: a diverged controller marked where it diverged, the stability figure's bounds as
in its title, and the replay map on a robust colour range that says so."""

from __future__ import annotations

import re
from types import SimpleNamespace

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch


@pytest.fixture
def figures(monkeypatch):
    """The figures the plotting functions close, kept for inspection."""
    kept = []
    monkeypatch.setattr(plt, "close", lambda fig=None: kept.append(fig))
    return kept


def run(level, diverged_frame=None, n=600):
    rms = level * (1 + 0.1 * np.random.default_rng(0).standard_normal(n))
    if diverged_frame is not None:
        rms[diverged_frame:] = level * np.exp(np.arange(n - diverged_frame))
    return SimpleNamespace(rms_nm=list(np.minimum(rms, 1e300)), diverged=diverged_frame is not None,
                           diverged_frame=diverged_frame, settle_frames=100)


def test_a_diverged_controller_is_drawn_until_it_diverged_and_marked(figures, tmp_path):
    from eofnn.evaluation.results import ExperimentResult
    from eofnn.reporting.report import plot_rms_vs_time

    result = ExperimentResult({"dm_gain_2": {"integrator": run(20.0), "ol_eof": run(2.0, diverged_frame=7)}})
    plot_rms_vs_time(result, 1000.0, tmp_path / "rms.png")
    ax = figures[-1].axes[0]
    curves = {line.get_label(): line for line in ax.lines}
    diverged = next(line for label, line in curves.items() if label.startswith("ol_eof (diverged at 0.007 s"))
    assert len(diverged.get_xdata()) == 8 and curves["integrator"].get_linestyle() != diverged.get_linestyle()
    markers = [line for line in ax.lines if line.get_marker() in ("X", "^")]
    assert len(markers) == 1 and markers[0].get_xdata()[0] == pytest.approx(0.007)
    assert ax.get_ylim()[1] <= 10 * 20.0 * 1.5  # the scale follows the loops that held


def test_the_stability_figure_marks_the_bounds_of_its_title(figures, tmp_path):
    from eofnn.analysis.stability import LoopSetup, analyse
    from eofnn.reporting.stability import plot_stability

    weights = torch.zeros(6, 4, dtype=torch.float64)
    weights[:, 0], weights[:, 1] = -1.0, 0.3
    weights += 0.15 * torch.randn(6, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    result = analyse(weights, "open_loop", 4, LoopSetup(delay_frames=2))
    lower, upper = result.gain_margin
    assert result.stable and int(result.gain_interval[:, 0].argmax()) != result.worst_group  # the case that disagreed
    plot_stability(result, tmp_path / "bode.png", "ol_eof")
    fig = figures[-1]
    title = fig._suptitle.get_text()
    labels = [line.get_label() for line in fig.axes[0].lines if line.get_label().startswith("DM gain")]
    assert f"({lower:.3g}, {upper:.3g})" in title and "\n" in title
    assert any(label.startswith(f"DM gain {lower:.3g} ") for label in labels), labels
    assert any(label.startswith(f"DM gain {upper:.3g} ") for label in labels), labels


@pytest.mark.slow
def test_the_replay_map_uses_a_robust_colour_range_and_says_so(figures, tmp_path):
    from eofnn.evaluation.replay import ErrorStats, ReplayResult
    from eofnn.reporting.replay import replay_figure
    from eofnn.sim.grid import ActuatorGrid

    grid = ActuatorGrid(2.0, 10)
    per_actuator = 3 + 0.3 * np.random.default_rng(1).standard_normal(grid.n_actuators)
    per_actuator[:2] = [80.0, 60.0]  # two edge actuators
    stats = ErrorStats(3.0, 3.0, 2.8, [3.0] * 100, list(per_actuator), [1.0] * 33, "")
    replay_figure(ReplayResult(stats, stats, 1.0, 100, 10, 1000.0, list(np.linspace(0, 500, 33))),
                  tmp_path / "replay.png", grid)
    image = figures[-1].axes[2].images[0]
    assert image.get_clim()[1] < 10 and "robust colour range" in image.colorbar.ax.get_ylabel()
    assert "2 actuators above" in image.colorbar.ax.get_ylabel()


def _metrics(level, diverged_frame=None, n=600):
    """A run with an RMS series, a residual PSD and a contrast profile (none of them when it diverged)."""
    from eofnn.evaluation.metrics import LoopMetrics

    r = run(level, diverged_frame, n)
    freqs, seps = list(np.linspace(0, 500, 65)), list(np.linspace(0.25, 4.75, 19))
    return LoopMetrics(None if r.diverged else level, None, None, None, r.diverged, diverged_frame, 100, n,
                       rms_nm=r.rms_nm, psd_freq_hz=[] if r.diverged else freqs,
                       psd_nm2_per_hz=[] if r.diverged else [level ** 2 / 500] * 65,
                       contrast_separation_lod=[] if r.diverged else seps,
                       contrast=[] if r.diverged else [1e-6 * level] * 19)


def _legend_texts(ax) -> list[str]:
    legend = ax.get_legend()
    return [] if legend is None else [t.get_text() for t in legend.get_texts()]


@pytest.mark.parametrize("figure", ["rms_vs_time", "rms_histograms", "psds", "contrast"])
def test_each_compare_figure_states_what_it_plots_and_names_every_contender(figures, tmp_path, figure):
    """Title, axes with units, the wavelength of the contrast, and every contender in each panel's legend: a
    diverged one by name and frame where it has no curve, never dropped silently."""
    from eofnn.evaluation.results import ExperimentResult
    from eofnn.reporting import report

    result = ExperimentResult({"nominal": {"integrator": _metrics(20.0), "ol_eof": _metrics(2.0)},
                               "dm_gain_2": {"integrator": _metrics(20.0), "ol_eof": _metrics(2.0, 7)}})
    draw = {"rms_vs_time": lambda p: report.plot_rms_vs_time(result, 1000.0, p),
            "rms_histograms": lambda p: report.plot_rms_histograms(result, p),
            "psds": lambda p: report.plot_psds(result, p),
            "contrast": lambda p: report.plot_contrast(result, p, 1.65e-6)}[figure]
    draw(tmp_path / "figure.png")
    fig = figures[-1]
    title = fig._suptitle.get_text()
    assert title
    nominal, doubled = fig.axes[0], fig.axes[1]
    assert (nominal.get_title(), doubled.get_title()) == ("nominal", "dm_gain_2")
    units = {"rms_vs_time": ("(s)", "(nm)"), "rms_histograms": ("(nm)", "frames"), "psds": ("(Hz)", "(nm²/Hz)"),
             "contrast": ("(λ/D)", "raw contrast")}[figure]
    assert units[0] in doubled.get_xlabel() and units[1] in nominal.get_ylabel()
    if figure == "contrast":
        assert "1.65 µm" in title
    for ax in (nominal, doubled):
        texts = _legend_texts(ax)
        assert any(t.startswith("integrator") for t in texts) and any(t.startswith("ol_eof") for t in texts), texts
    if figure != "rms_vs_time":  # there the diverged run is drawn up to its divergence and marked (test above)
        assert "ol_eof: diverged (frame 7)" in _legend_texts(doubled)
        assert "ol_eof" in _legend_texts(nominal)


def test_the_stability_figure_titles_its_panels_and_defines_its_symbols(figures, tmp_path):
    from eofnn.analysis.stability import LoopSetup, analyse
    from eofnn.reporting.stability import plot_stability

    weights = torch.zeros(6, 4, dtype=torch.float64)
    weights[:, 0], weights[:, 1] = -1.0, 0.3
    weights += 0.15 * torch.randn(6, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    plot_stability(analyse(weights, "open_loop", 4, LoopSetup(delay_frames=2)), tmp_path / "bode.png", "ol_eof")
    fig = figures[-1]
    rejection, noise = fig.axes[:2]
    assert "rejection" in rejection.get_title().lower() and "noise" in noise.get_title().lower()
    assert all(ax.get_xlabel() == "frequency (Hz)" for ax in (rejection, noise))
    assert "WFS noise" in noise.get_ylabel() and "turbulence" in rejection.get_ylabel()
    labels = [t for ax in (rejection, noise) for t in _legend_texts(ax)]
    assert not any(re.search(r"\bgroup \d", t) for t in labels), labels  # an actuator, not an internal "group"
    assert any(t.startswith("least stable: actuator ") for t in labels)
    footnote = " ".join(t.get_text() for t in fig.texts)
    assert "v: white WFS noise (nm)" in footnote and "s: turbulence (nm)" in footnote


def test_the_replay_figure_uses_a_log_axis_for_the_per_frame_error(figures, tmp_path):
    """A 300 nm first frame must not flatten a 2 nm curve."""
    from eofnn.evaluation.replay import ErrorStats, ReplayResult
    from eofnn.reporting.replay import replay_figure

    rms = [300.0, 80.0] + [2.0 + 0.1 * np.sin(i) for i in range(98)]
    stats = ErrorStats(2.0, 2.0, 1.9, rms, [2.0] * 4, [1.0] * 33, "")
    replay_figure(ReplayResult(stats, stats, 1.0, 100, 10, 1000.0, list(np.linspace(0, 500, 33))),
                  tmp_path / "replay.png")
    per_frame, psd = figures[-1].axes[:2]
    assert per_frame.get_yscale() == "log" and "(nm" in per_frame.get_ylabel() and per_frame.get_title()
    assert psd.get_title() and "(Hz)" in psd.get_xlabel() and "(nm²/Hz)" in psd.get_ylabel()
    assert any(t.startswith("predictor (median 2 nm)") for t in _legend_texts(per_frame))


@pytest.mark.parametrize("figure", ["psds", "contrast"])
def test_a_single_panel_figure_keeps_its_whole_title(figures, tmp_path, figure):
    """One scenario makes a narrow figure: its long title is wrapped, never clipped at the sides."""
    from eofnn.evaluation.results import ExperimentResult
    from eofnn.reporting import report

    result = ExperimentResult({"nominal": {"integrator": _metrics(20.0), "ol_eof": _metrics(2.0)}})
    {"psds": lambda p: report.plot_psds(result, p),
     "contrast": lambda p: report.plot_contrast(result, p, 1.65e-6)}[figure](tmp_path / "figure.png")
    fig = figures[-1]
    fig.canvas.draw()
    box = fig._suptitle.get_window_extent()
    assert box.x0 >= 0 and box.x1 <= fig.bbox.width, (box, fig.bbox.width)
