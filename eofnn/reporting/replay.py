"""``replay.png``: a replay of a predictor on held-out telemetry (:func:`eofnn.evaluation.replay.replay`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import torch

from eofnn.evaluation.replay import ReplayResult
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.layout import ActuatorLayout


def replay_figure(result: ReplayResult, path: str | Path, grid: ActuatorGrid | ActuatorLayout | None = None) -> Path:
    """RMS per frame, the predictor's error map per actuator (needs ``grid``: an image on eofnn's grid, a scatter
    at the positions of another layout) and the temporal PSDs, in one PNG."""
    panels = 3 if grid is not None else 2
    fig, axes = plt.subplots(1, panels, figsize=(5 * panels, 4))
    curves = ((result.predictor, "predictor", "-"), (result.own_controller, "telemetry's controller", "--"))
    for stats, label, style in curves:  # distinct styles: the two may lie on top of each other
        axes[0].plot(stats.rms_nm, style, lw=0.6, label=f"{label} (median {stats.median_rms_nm:.3g} nm)")
        if stats.psd_nm2_per_hz:
            axes[1].loglog(result.psd_freq_hz[1:], stats.psd_nm2_per_hz[1:], style, label=label)
    # A log axis: the first replayed frames (the filter's history filling) can be 100x the settled error, and a
    # linear axis would flatten the curve that matters against them.
    axes[0].set_yscale("log")
    axes[0].set(xlabel="replayed frame", ylabel="RMS error (nm, log scale)", title="prediction error per frame")
    axes[1].set(xlabel="frequency (Hz)", ylabel="PSD (nm²/Hz)", title="temporal PSD")
    for ax in axes[:2]:
        ax.legend(fontsize=8)
    if isinstance(grid, ActuatorGrid):
        values = torch.tensor(result.predictor.map_rms_nm, dtype=torch.float64)
        image = grid.to_map(values).numpy()
        # A robust colour range: a few edge actuators (extruded columns, rims) would otherwise swamp the scale.
        # From the 1st percentile to the 99th, or to median + 6 MAD (sigma-equivalent) when that is lower.
        finite = values[values.isfinite()]
        low, high = (float(q) for q in torch.quantile(finite, torch.tensor([0.01, 0.99], dtype=torch.float64)))
        median = float(finite.median())
        spread = 1.4826 * float((finite - median).abs().median())
        if spread > 0:
            high = min(high, median + 6 * spread)
        shown = axes[2].imshow(image, origin="lower", vmin=low, vmax=max(high, low + 1e-12))
        above = int((finite > high).sum())
        fig.colorbar(shown, ax=axes[2], extend="max" if above else "neither",
                     label=f"RMS error (nm); robust colour range\n({above} actuators above {high:.3g} nm)")
        axes[2].set(title="predictor error per actuator", xlabel="x (actuators)", ylabel="y (actuators)")
    elif grid is not None:
        x, y = grid.positions_m.T
        shown = axes[2].scatter(x, y, c=result.predictor.map_rms_nm, s=12)
        fig.colorbar(shown, ax=axes[2], label="RMS error (nm)")
        axes[2].set(title="predictor error per actuator", xlabel="x (m)", ylabel="y (m)", aspect="equal")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
