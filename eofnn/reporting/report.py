"""Results as people read them: a Markdown table and figures (RMS against time, RMS histograms, residual PSDs)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from eofnn.evaluation.results import ExperimentResult, describe_setting_scan
from eofnn.reporting.verdict import dm_gain_interval_text, unstable_text, verdict_markdown
from eofnn.training.alpha import NEGLIGIBLE_CHANGE, unregularised_change


def _cell(m) -> str:
    if m.diverged:
        return f"diverged (frame {m.diverged_frame})"
    if getattr(m, "diverging", False):
        return f"{m.median_rms_nm:.3g}, diverging ({m.growth['growth_rate_per_s']:+.2g}/s)"
    return f"{m.median_rms_nm:.3g}"


def strehl_label(wavelength_m: float | None) -> str:
    """``Strehl at 1.65 um``: a Strehl ratio means nothing without its wavelength."""
    return "Strehl" if wavelength_m is None else f"Strehl at {wavelength_m * 1e6:.3g} um"


def markdown_table(result: ExperimentResult, reference: dict[str, dict[str, float]] | None = None,
                   strehl_wavelength_m: float | None = None) -> str:
    """Median RMS (nm) per predictor (rows) and scenario (columns); ``reference`` adds the study's numbers."""
    scenarios = list(result.metrics)
    predictors = list(next(iter(result.metrics.values())))
    over = " over the pupil" if getattr(next(iter(result.metrics[scenarios[0]].values())), "residual_over", "") == "pupil" else ""
    header = ["predictor"] + [f"{s} median RMS{over} (nm)" for s in scenarios]
    if reference:
        header += [f"{s} study (nm)" for s in scenarios]
    header += [f"{s} p95 (nm)" for s in scenarios] + [f"{s} {strehl_label(strehl_wavelength_m)}" for s in scenarios]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for p in predictors:
        row = [p] + [_cell(result.metrics[s][p]) for s in scenarios]
        if reference:
            row += [f"{reference[s][p]:g}" if p in reference.get(s, {}) else "" for s in scenarios]
        for key in ("p95_rms_nm", "strehl"):
            for s in scenarios:
                value = getattr(result.metrics[s][p], key)
                row.append("—" if value is None else f"{value:.3g}")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


#: Line styles cycled with the colours, so that curves lying on top of each other stay distinguishable.
_STYLES = ("-", "--", "-.", ":")


def _styles(result: ExperimentResult) -> dict[str, dict]:
    """One colour and one line style per controller, the same in every panel and figure."""
    names = list(dict.fromkeys(p for preds in result.metrics.values() for p in preds))
    return {name: {"color": f"C{i % 10}", "linestyle": _STYLES[i % len(_STYLES)]} for i, name in enumerate(names)}


def _legend(ax) -> None:
    """Each panel's legend below it, so that it never hides a curve."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3, frameon=False)


def _mark_missing(ax, name: str, m, what: str) -> None:
    """A legend entry (no curve) for a controller a panel cannot draw, so that it is never dropped silently: where it
    diverged, or that it has no ``what``."""
    why = (f"diverged (frame {m.diverged_frame})" if m.diverged and m.diverged_frame is not None else
           "diverged" if m.diverged else f"no {what}")
    ax.plot([], [], " ", label=f"{name}: {why}")


def _figure(result: ExperimentResult, path: Path, title: str, xlabel: str, ylabel: str, draw) -> None:
    """One panel per scenario, wrapped into rows of at most three: ``draw(ax, predictors, styles)`` fills each;
    titles, legends and saving are shared."""
    n = len(result.metrics)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.5 * cols, 4.8 * rows), squeeze=False, sharey=True)
    fig.suptitle(textwrap.fill(title, width=int(12 * 5.5 * cols)))  # about 12 characters an inch: never clipped
    styles = _styles(result)
    flat = axes.ravel()
    for ax, (scenario, preds) in zip(flat, result.metrics.items(), strict=False):
        draw(ax, preds, styles)
        ax.set_title(scenario)
        ax.set_xlabel(xlabel)
        _legend(ax)
    for ax in flat[n:]:
        ax.set_visible(False)
    for row in axes:
        row[0].set_ylabel(ylabel)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_rms_vs_time(result: ExperimentResult, frame_rate_hz: float, path: Path) -> None:
    """Spatial RMS residual against time, log scale, one panel per scenario (like the study's Figure 3)."""

    def draw(ax, preds, styles):
        # The y range follows the loops that held: a diverged one is drawn until it diverged, clipped at the top,
        # and marked where it diverged (an X, or a triangle at the top edge when that point is off the scale).
        held = [np.asarray(m.rms_nm, dtype=float) for m in preds.values() if not m.diverged and len(m.rms_nm)]
        finite = np.concatenate([r[np.isfinite(r)] for r in held]) if held else np.array([])
        top = 10 * finite.max() if finite.size else None
        for name, m in preds.items():
            rms = np.asarray(m.rms_nm, dtype=float)
            if rms.size == 0:
                continue
            if m.diverged and m.diverged_frame is not None:
                rms = rms[:max(1, min(m.diverged_frame + 1, rms.size))]
            t = np.arange(rms.size) / frame_rate_hz
            label = name + (f" (diverged at {m.diverged_frame / frame_rate_hz:.3g} s, marked)" if m.diverged else "")
            shown = np.maximum(np.nan_to_num(rms, nan=np.inf, posinf=np.inf), 1e-6)
            ax.semilogy(t, shown, lw=0.8, label=label, **styles[name])
            if m.diverged:
                last = shown[np.isfinite(shown)][-1] if np.isfinite(shown).any() else np.inf
                off_scale = top is not None and last > top
                ax.plot(t[-1], top / 1.3 if off_scale else last, marker="^" if off_scale else "X", ms=9,
                        color=styles[name]["color"], markeredgecolor="k", linestyle="none", zorder=5)
        if top is not None:
            ax.set_ylim(top=top)
        settle_s = next(iter(preds.values())).settle_frames / frame_rate_hz
        if settle_s > 0:
            ax.axvspan(0, settle_s, color="0.9", zorder=0, label="settling (not in the statistics)")
        ax.grid(True, which="both", alpha=0.3)

    _figure(result, path, "Residual spatial RMS", "time (s)", "RMS residual (nm)", draw)


def plot_rms_histograms(result: ExperimentResult, path: Path) -> None:
    """Histograms of the settled per-frame RMS (log bins), one panel per scenario."""

    def draw(ax, preds, styles):
        settled = {n: np.asarray(m.rms_nm)[m.settle_frames:] for n, m in preds.items() if not m.diverged}
        values = np.concatenate([v for v in settled.values() if v.size]) if settled else np.array([])
        if values.size:
            bins = np.logspace(np.log10(max(values.min(), 1e-6)), np.log10(values.max()) + 1e-9, 60)
            for name, v in settled.items():
                ax.hist(v, bins=bins, histtype="step", label=name, **styles[name])
            ax.set_xscale("log")
        for name, m in preds.items():
            if m.diverged:
                _mark_missing(ax, name, m, "settled frames")

    _figure(result, path, "Distribution of per-frame RMS residual (after settling)", "RMS residual (nm)", "frames",
            draw)


def _curves_figure(result: ExperimentResult, path: Path, x: str, y: str, floor: float, log_x: bool, lw: float,
                   title: str, xlabel: str, ylabel: str, what: str) -> None:
    """One curve per controller that did not diverge, of its ``y`` list against its ``x`` list (first point dropped,
    log y clipped at ``floor``), one panel per scenario; a controller without a curve (diverged, or no ``what``) is
    named in the legend with the reason."""

    def draw(ax, preds, styles):
        for name, m in preds.items():
            if getattr(m, y) and not m.diverged:
                xs, ys = np.asarray(getattr(m, x))[1:], np.asarray(getattr(m, y))[1:]
                (ax.loglog if log_x else ax.semilogy)(xs, np.maximum(ys, floor), lw=lw, label=name, **styles[name])
            else:
                _mark_missing(ax, name, m, what)
        ax.grid(True, which="both", alpha=0.3)

    _figure(result, path, title, xlabel, ylabel, draw)


def plot_psds(result: ExperimentResult, path: Path) -> None:
    """Temporal PSD of the residual (mean over actuators), one panel per scenario; the title says which residual
    (:attr:`~eofnn.evaluation.metrics.LoopMetrics.psd_residual`)."""
    kinds = {getattr(m, "psd_residual", "eps") for preds in result.metrics.values() for m in preds.values()}
    which = ("against the DM's fit of the true phase, P F phi + DM(y)" if kinds == {"dm_fit"} else
             "s + DM(y)" if kinds == {"eps"} else "s + DM(y), or P F phi + DM(y) where scored over the pupil")
    _curves_figure(result, path, "psd_freq_hz", "psd_nm2_per_hz", 1e-30, True, 0.8,
                   f"Temporal power spectrum of the residual {which} (mean over actuators, piston included, after "
                   "settling)", "frequency (Hz)", "PSD (nm²/Hz)", "PSD (run shorter than one segment)")


def plot_contrast(result: ExperimentResult, path: Path, wavelength_m: float | None) -> None:
    """Raw contrast behind a perfect coronagraph against separation, one panel per scenario, at ``wavelength_m``
    (the ``evaluation.strehl_wavelength_m`` the contrast was computed at; a contrast means nothing without it)."""
    at = "wavelength not given" if wavelength_m is None else f"at {wavelength_m * 1e6:.3g} µm"
    _curves_figure(result, path, "contrast_separation_lod", "contrast", 1e-18, False, 0.9,
                   f"Raw contrast behind a perfect coronagraph, {at} (after settling)", "separation (λ/D)",
                   "raw contrast (intensity / unobstructed PSF peak)", "contrast profile")


def _caveat(result: ExperimentResult) -> str:
    """Sub-nanometre residuals need a word beside them: they describe the simulator, not the predictor."""
    small = sorted({p for preds in result.metrics.values() for p, m in preds.items()
                    if m.median_rms_nm is not None and m.median_rms_nm < 1.0})
    if not small:
        return ""
    return (f"\nNote: {', '.join(small)} reach below 1 nm. Without WFS noise such a floor is set by how the "
            "simulator builds the turbulence (interpolation, sampling and sensing of the screen), not by the "
            "predictor: different constructions of the same atmosphere span 0.004 nm to 30 nm, and with 1 nm or more "
            "of WFS noise they agree within about 25%. Compare sub-nanometre numbers with a study's only for the "
            "same turbulence construction, and look at the residual PSD (residual_psd.png) before believing them.\n")


def _gains(result: ExperimentResult) -> str:
    """A line per best-gain integrator: the gain chosen in each scenario."""
    lines = []
    for scenario, scans in result.integrator_gains.items():
        for name, scan in scans.items():
            edge = (f"; at the edge of what was tried (critical gain {scan['critical_gain']:.3g})"
                    if scan.get("at_edge") else "")
            if not edge and "critical_gain" in scan and scan["gain"] >= 0.98 * scan["critical_gain"]:
                edge = f"; within 2% of the critical gain {scan['critical_gain']:.3g}"
            lines.append(f"- {name} in {scenario}: gain {scan['gain']:g} (best of {', '.join(scan['scanned'])}{edge})")
    if not lines:
        return ""
    return "\nBest-gain integrators (chosen on a stream of their own, not the test stream):\n" + "\n".join(lines) + "\n"


def _classical_settings(result: ExperimentResult) -> str:
    """A line per tuned classical controller and scenario: the setting chosen (an extrapolator's order, an LQG's AR
    order), over the others tried."""
    lines = [f"- {name} in {scenario}: {describe_setting_scan(scan)}"
             for scenario, scans in result.classical_settings.items() for name, scan in scans.items()]
    if not lines:
        return ""
    return ("\nTuned classical controllers (settings chosen on a stream of their own, not the test stream; median "
            "residual there, nm):\n" + "\n".join(lines) + "\n")


def _fallbacks(result: ExperimentResult) -> str:
    """A line per guarded controller and scenario: what was deployed, on how many modes, and why."""
    lines = []
    for scenario, decisions in result.fallbacks.items():
        for name, report in decisions.items():
            modes = ""
            if "n_modes" in report:
                fallen = report["fallen_back"]
                modes = (f"; the predictor won {report['predictor_modes']} of {report['n_modes']} "
                         f"{'KL modes' if report['modes'] == 'kl' else 'actuators'}, {len(fallen['worse'])} fell "
                         f"back as worse and {len(fallen['within_scatter'])} as no "
                         "better than the scatter")
            lines.append(f"- {name} in {scenario}: **{report['deployed']}** deployed (per {report['per']}, integrator "
                         f"gain {report['integrator_gain']:g}{modes}): {report['why']}")
    if not lines:
        return ""
    return ("\nFallbacks to the best-gain integrator (decided on a validation stream of their own, not the test "
            "stream; which modes: metrics.json `fallback`):\n" + "\n".join(lines) + "\n")


def _fixed_gains(result: ExperimentResult) -> str:
    """A line per integrator run at the gain its config fixed (not chosen): what it ran at, and how to ask for the
    best gain instead."""
    fixed: dict[str, dict[str, float]] = {}
    for scenario, used in result.integrator_gain_used.items():
        for name, entry in used.items():
            if not entry["scanned"]:
                fixed.setdefault(name, {})[scenario] = entry["gain"]
    if not fixed:
        return ""
    lines = [f"- {name}: gain {', '.join(sorted({f'{g:g}' for g in by_scenario.values()}))} in "
             f"{', '.join(by_scenario)}" for name, by_scenario in fixed.items()]
    return ("\nIntegrators at a fixed gain (not tuned: `{controller: integrator, gains: [...]}`, or `eofnn evaluate "
            "--integrator.gains '[...]'`, closes the loop with each gain and keeps the best):\n" + "\n".join(lines) + "\n")


def _alpha_edge(choice: dict) -> str:
    """What an alpha at an end of its path means: the unregularised fit's validation error beside it at the lower
    end (when they agree, no smaller alpha can matter), a hint to extend the path otherwise."""
    if not choice.get("at_edge"):
        return ""
    change = unregularised_change(choice)
    if change is None:
        return "; at an end of the path: extend alpha_path to look beyond it"
    if abs(change) < NEGLIGIBLE_CHANGE:
        return (f"; at the path's lower end, where the unregularised fit's validation error differs by {change:+.1e} "
                "of it: a smaller alpha would barely matter")
    return (f"; at the path's lower end, and the unregularised fit's validation error differs by {change:+.2%}: "
            "extend alpha_path below it")


def _alphas(result: ExperimentResult) -> str:
    """A line per ridge alpha chosen on validation data (``alpha: auto``)."""
    lines = []
    for scenario, choices in result.ridge_alphas.items():
        for name, choice in choices.items():
            where = ("" if "dm_gain_interval" not in choice
                     else "; stable for DM gain {:.3g} to {:.3g}".format(*choice["dm_gain_interval"]))
            where += _alpha_edge(choice)
            lines.append(f"- {name} trained in {scenario}: alpha {choice['alpha']:g} (least validation error of "
                         f"{len(choice['path']['alpha'])} from {choice['path']['alpha'][0]:g} to "
                         f"{choice['path']['alpha'][-1]:g}{where})")
    for scenario, searches in result.searches.items():
        for name, searched in searches.items():
            chosen, budget = searched["chosen"], searched["budget"]
            width = "" if chosen["width"] is None else f", width {chosen['width']}"
            lines.append(f"- {name} trained in {scenario}: lr {chosen['lr']:g}{width}, best epoch {chosen['best_epoch']} "
                         f"(least validation loss of {budget['trials']} trials; budget {budget['epochs']} epochs, "
                         f"{budget['frames']} frames)")
    if not lines:
        return ""
    return ("\nTuning (ridge alphas and network searches, chosen on validation data, not the test stream):\n"
            + "\n".join(lines) + "\n")


def _margins(result: ExperimentResult) -> str:
    """The stable DM-gain interval of every controller in every scenario: analytic (linear controllers) or measured
    by simulation (networks, where asked)."""
    lines = []
    for scenario, preds in result.metrics.items():
        for name in preds:
            analytic = result.stability.get(scenario, {}).get(name)
            simulated = result.simulated_stability.get(scenario, {}).get(name)
            dm_gain = result.scenario_dm_gains.get(scenario)
            if analytic is not None:
                text = (f"{unstable_text(dm_gain)} (linear analysis)" if not analytic["stable"] else
                        f"stable for DM gain {dm_gain_interval_text(analytic['dm_gain_interval'])} (linear analysis)")
            elif simulated is not None:
                interval = simulated["dm_gain_interval"]
                text = (f"{unstable_text(dm_gain)} (simulation)" if interval is None else
                        f"stable for DM gain {interval[0]:.3g} to "
                        f"{'beyond 8' if interval[1] is None else f'{interval[1]:.3g}'} "
                        f"(simulation, bounds within {simulated['tolerance']:g})")
            else:
                continue
            lines.append(f"- {name} in {scenario}: {text}")
    if not lines:
        return ""
    return "\nStable DM-gain intervals (the DM applying g times the command):\n" + "\n".join(lines) + "\n"


def _budget(result: ExperimentResult) -> str:
    """The error budget of every contender that has one (:mod:`eofnn.evaluation.budget`), per scenario."""
    lines = []
    for scenario, contenders in result.metrics.items():
        rows = [(name, m.error_budget) for name, m in contenders.items() if getattr(m, "error_budget", None)]
        if not rows:
            continue
        over = next(iter(contenders.values())).residual_over
        lines += ["", f"Error budget in {scenario} (median residual, nm, over the {over}; split in quadrature from "
                      "runs without noise and with a perfect sensor: evaluation.error_budget):", "",
                  "| contender | fitting | aliasing | noise | temporal | total |", "|---|---|---|---|---|---|"]
        for name, budget in rows:
            cells = ["n/a" if budget[k] is None and k in ("fitting_nm", "aliasing_nm") else
                     "—" if budget[k] is None else f"{budget[k]:.1f}"
                     for k in ("fitting_nm", "aliasing_nm", "noise_nm", "temporal_nm")]
            total = budget["runs_nm"]["total"]
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {'—' if total is None else f'{total:.1f}'} |")
    return "\n".join(lines) + "\n" if lines else ""


def _spatial(result: ExperimentResult) -> str:
    """Where in spatial frequency each contender's residual lies (:meth:`RawContrast.spatial_split`), per scenario:
    only where some residual lies beyond the control square (a Shack-Hartmann scenario's fine grid)."""
    lines = []
    for scenario, contenders in result.metrics.items():
        rows = [(name, m.spatial_split_nm) for name, m in contenders.items() if getattr(m, "spatial_split_nm", None)]
        if not rows or not any(split["beyond_control"] > 0 for _, split in rows):
            continue
        lines += ["", f"Where the residual lies in {scenario} (RMS over the pupil, nm, on the frames the contrast "
                      "propagates; the three add in quadrature): inside the control radius's circle, in the corners "
                      "of the DM's square control region, beyond the square:", "",
                  "| contender | inside the circle | square's corners | beyond the square |", "|---|---|---|---|"]
        lines += [f"| {name} | {split['inside_control_circle']:.1f} | {split['control_square_corners']:.1f} | "
                  f"{split['beyond_control']:.1f} |" for name, split in rows]
    return "\n".join(lines) + "\n" if lines else ""


def write_report(result: ExperimentResult, out: Path, frame_rate_hz: float,
                 reference: dict[str, dict[str, float]] | None = None,
                 strehl_wavelength_m: float | None = None) -> list[Path]:
    """Write ``results.md`` (the verdict first, when ``result`` has one) and the four figures into ``out``; returns the
    paths written."""
    table = out / "results.md"
    verdict = "" if result.verdict is None else verdict_markdown(result.verdict) + "\n"
    table.write_text("# Closed-loop comparison\n\n" + verdict + "## Median RMS per scenario\n\n"
                     + markdown_table(result, reference, strehl_wavelength_m)
                     + _gains(result) + _fixed_gains(result) + _classical_settings(result) + _fallbacks(result)
                     + _alphas(result)
                     + _margins(result) + _budget(result) + _spatial(result) + _caveat(result))
    figures = [out / "rms_vs_time.png", out / "rms_histogram.png", out / "residual_psd.png", out / "contrast.png"]
    plot_rms_vs_time(result, frame_rate_hz, figures[0])
    plot_rms_histograms(result, figures[1])
    plot_psds(result, figures[2])
    plot_contrast(result, figures[3], strehl_wavelength_m)
    return [table, *figures]
