"""``pareto.png``: performance beside robustness along each linear family's tuning path
(:func:`eofnn.evaluation.pareto.pareto`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt

from eofnn.evaluation.pareto import ParetoResult


def plot_pareto(result: ParetoResult, path: Path) -> None:
    """``pareto.png``: median RMS (log) against the stable DM-gain interval's width, a curve per family."""
    fig, ax = plt.subplots(figsize=(7, 5))
    markers = "osD^v<>ph*"
    for i, (name, points) in enumerate(result.families.items()):
        drawn = [p for p in points if p["median_rms_nm"] is not None and p["width"] is not None]
        drawn.sort(key=lambda p: p["width"])
        style = {"color": f"C{i % 10}", "marker": markers[i % len(markers)]}
        ax.plot([p["width"] for p in drawn], [p["median_rms_nm"] for p in drawn], linestyle="-", label=name,
                alpha=0.8, **style)
        for p in drawn:
            if result.required is not None and not p.get("meets"):  # hollow: not stable over the asked interval
                ax.plot(p["width"], p["median_rms_nm"], markerfacecolor="white", linestyle="none", **style)
            if p["chosen"]:
                ax.plot(p["width"], p["median_rms_nm"], markersize=14, markerfacecolor="none", linestyle="none",
                        markeredgewidth=1.5, **style)
    ax.set_yscale("log")
    ax.set_xlabel("width of the stable DM-gain interval (relative to the plant's DM gain)")
    ax.set_ylabel("median RMS residual (nm)")
    asked = ("" if result.required is None else
             "; hollow marker: not stable over DM gain [{:g}, {:g}]".format(*result.required))
    ax.set_title(f"Performance beside robustness, {result.scenario}\n(large circle: chosen setting{asked})", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
