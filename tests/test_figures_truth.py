"""Figures that tell the truth: a diverged controller marked where it diverged, the stability figure's bounds as
in its title, and the replay map on a robust colour range that says so."""

from __future__ import annotations

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
