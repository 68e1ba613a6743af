"""Figures of the analysis: Bode-style plots of a stability result."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt

from eofnn.analysis.stability import StabilityResult

#: What each panel plots: title and y label. ``s`` is the turbulence, ``v`` the WFS noise and ``eps`` the residual, all
#: in nm, so both ratios are dimensionless.
PANELS = (("Turbulence rejection: residual / turbulence", "|eps / s|  (per nm of turbulence)"),
          ("Noise transfer: residual / WFS noise v", "|eps / v|  (per nm of WFS noise)"))

#: Below the panels: the symbols, with their units.
SYMBOLS = ("s: turbulence (nm), v: white WFS noise (nm), eps: residual (nm); the horizontal line at 1 is no "
           "attenuation")


def group_name(result: StabilityResult, group: int) -> str:
    """A group of the analysis in words: an actuator's own filter, the shared filter, or the coupled system."""
    if result.structure == "per_actuator":
        return f"actuator {group}"
    if result.structure == "shared":
        return "the shared filter"
    return "the coupled system" if len(result.max_root_modulus) == 1 else f"filter group {group}"


def plot_stability(result: StabilityResult, path: str | Path, title: str = "") -> Path:
    """|rejection| and |noise transfer| against frequency for the least stable and the median group (an actuator's
    filter, the shared filter or the coupled system), with margins; symbols and units are defined under the panels.

    Dotted (lower) and dash-dotted (upper) vertical lines mark the frequencies at which a pole leaves the unit circle
    at either end of the DM gain interval, each for the group that sets that end; the interval (every group stable
    within it) and the delay margin are in the title.
    """
    path = Path(path)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharex=True)
    freqs = result.frequencies_hz.numpy()
    lower, upper = result.gain_margin
    worst, median = result.worst_group, result.median_group
    if result.rejection.numel():
        curves = ((worst, f"least stable: {group_name(result, worst)}", "-"),
                  (median, f"median margin: {group_name(result, median)}", "--"))
        for group, label, style in curves:
            axes[0].loglog(freqs, result.rejection[group].abs().numpy(), style, label=label)
            axes[1].loglog(freqs, result.noise_transfer[group].abs().numpy(), style, label=label)
        # Each bound of the title's interval is set by one group (the lower by the group with the highest lower
        # bound, the upper by the lowest upper): mark the frequency at which that group's pole leaves there.
        for end, pick, style in ((0, result.gain_interval[:, 0].argmax(), ":"),
                                 (1, result.gain_interval[:, 1].argmin(), "-.")):
            group = int(pick)
            bound = float(result.gain_interval[group, end])
            crossing = float(result.gain_crossing_hz[group, end])
            if crossing == crossing and crossing > 0 and bound == bound:  # not NaN; 0 Hz is off a log axis
                for ax in axes:
                    ax.axvline(crossing, color="grey", linestyle=style,
                               label=f"DM gain {max(bound, 0.0) + 0.0:.3g} ({group_name(result, group)}): a pole "
                                     f"leaves at {crossing:.3g} Hz")
    else:
        for ax in axes:
            ax.text(0.5, 0.5, "transfer functions not computed\n(coupled system too large)", ha="center",
                    transform=ax.transAxes)
    for ax, (panel_title, ylabel) in zip(axes, PANELS, strict=True):
        ax.axhline(1.0, color="black", linewidth=0.6)
        ax.set_title(panel_title, fontsize=10)
        ax.set_xlabel("frequency (Hz)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    each = "actuator" if result.structure == "per_actuator" else "filter"
    status = (f"stable, DM gain in ({max(lower, 0.0) + 0.0:.3g}, {upper:.3g}) for every {each}, delay margin "
              f"{float(result.delay_margin_frames.min()):.3g} frames" if result.stable else
              f"UNSTABLE (max pole modulus {float(result.max_root_modulus.max()):.4g})")
    # Two lines, inside the figure: one line of this length is wider than the figure and was cut off.
    fig.suptitle(f"{title + ': ' if title else ''}{result.kind} {result.structure}, p={result.history_length}, "
                 f"delay {result.setup.delay_frames:g} frames, DM gain {result.setup.dm_gain:g}\n{status}", fontsize=10)
    fig.text(0.5, 0.01, SYMBOLS, ha="center", fontsize=8)
    fig.tight_layout(rect=(0, 0.04, 1, 0.92))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
