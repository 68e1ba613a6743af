"""``robustness.png``: the robustness map of :func:`eofnn.evaluation.robustness.robustness_map`."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from eofnn.evaluation.robustness import RobustnessResult


def plot_robustness(result: RobustnessResult, path: Path) -> None:
    """1-D: median RMS against the plant field, diverged points as crosses on top, analytic DM gain bounds as
    dashed lines; 2-D: one map per controller with diverged cells crossed."""
    names = list(result.median_rms_nm)
    if len(result.keys) == 1:
        fig, ax = plt.subplots(figsize=(7.5, 5))
        x = np.asarray(result.values[0])
        finite = [v for vals in result.median_rms_nm.values() for v in vals if v is not None]
        top = max(finite) * 3 if finite else 1.0
        for i, name in enumerate(names):
            colour, style = f"C{i % 10}", ("-", "--", "-.", ":")[i % 4]
            y = np.array([np.nan if v is None else v for v in result.median_rms_nm[name]])
            ax.semilogy(x, y, marker="o", color=colour, linestyle=style, label=name)
            bad = np.isnan(y)
            if bad.any():
                ax.scatter(x[bad], np.full(bad.sum(), top * 1.4 ** i), marker="x", s=60, color=colour)
            if result.keys[0] == "dm_gain" and name in result.dm_gain_interval:
                for bound in result.dm_gain_interval[name]:
                    if bound is not None and x.min() <= bound <= x.max():
                        ax.axvline(bound, color=colour, linestyle=":", lw=1)
        ax.set_xlabel(result.keys[0])
        ax.set_ylabel("median RMS residual (nm)")
        ax.set_title(f"Robustness of the controllers made for '{result.scenario}'\n"
                     "crosses on top: diverged; dotted lines: analytic stability bounds")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=3, frameon=False)
    else:
        cols = min(len(names), 3)
        rows = -(-len(names) // cols)
        fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 4.2 * rows), squeeze=False)
        shape = (len(result.values[0]), len(result.values[1]))
        for ax, name in zip(axes.ravel(), names, strict=False):
            grid = np.array([np.nan if v is None else v for v in result.median_rms_nm[name]]).reshape(shape)
            image = ax.imshow(np.log10(grid.T), origin="lower", aspect="auto", cmap="viridis")
            for (i, j), v in np.ndenumerate(grid):
                if np.isnan(v):
                    ax.text(i, j, "×", ha="center", va="center", color="red", fontsize=12)
            ax.set_xticks(range(shape[0]), [f"{v:g}" for v in result.values[0]])
            ax.set_yticks(range(shape[1]), [f"{v:g}" for v in result.values[1]])
            ax.set_xlabel(result.keys[0])
            ax.set_ylabel(result.keys[1])
            ax.set_title(name)
            fig.colorbar(image, ax=ax, label="log10 median RMS (nm)")
        for ax in axes.ravel()[len(names):]:
            ax.set_visible(False)
        fig.suptitle(f"Robustness of the controllers made for '{result.scenario}' (×: diverged)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
