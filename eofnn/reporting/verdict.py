"""The verdict as people read it: the first section of ``results.md``, written from ``metrics.json``'s ``verdict``
(:func:`eofnn.evaluation.verdict.build_verdict`), so the two can never disagree."""

from __future__ import annotations


def _nm(value: float) -> str:
    return f"{value:.3g} nm"


def _times(ratio: float) -> str:
    """A ratio as people say it, never rounded away: two decimals below 10 (``1.02x``, ``2.16x``), one below 100
    (``52.4x``), whole numbers above."""
    return f"{ratio:.2f}x" if ratio < 10 else f"{ratio:.1f}x" if ratio < 100 else f"{ratio:.0f}x"


def _spread(spread: dict | None, fmt=_times) -> str:
    """`` (1.48x to 1.62x over 3 realisations)``; empty without a spread."""
    if spread is None:
        return ""
    if spread["min"] is None:
        return " (not defined in every realisation)"
    return f" ({fmt(spread['min'])} to {fmt(spread['max'])} over {len(spread['per_realisation'])} realisations)"


def _ratio_or_none(value: float | None, spread: dict | None) -> str:
    return "not defined" if value is None else _times(value) + _spread(spread)


def _eta_text(value: float) -> str:
    return f"{value:.3g}"


def _predictor_ratio_text(name: str, r: dict, fitting_nm: float | None) -> str:
    """One predictor's ratios over the best classical controller, the plain variance ratio first."""
    parts = [f"variance {_ratio_or_none(r['variance_ratio'], r['variance_ratio_spread'])}",
             f"RMS {_ratio_or_none(r['rms_ratio'], r['rms_ratio_spread'])}"]
    if fitting_nm is not None:
        parts.append(f"variance after fitting error ({fitting_nm:.3g} nm, estimated as said below) "
                     + _ratio_or_none(r["after_fitting_variance_ratio"], r["after_fitting_variance_ratio_spread"]))
    contrast = [f"{_ratio_or_none(c['ratio'], c['spread'])} at {sep} λ/D (against {c['against']}, the best classical "
                f"controller in contrast there: {c['against_contrast']:.2g} against {c['contrast']:.2g})"
                for sep, c in r["raw_contrast"].items() if c is not None]
    missing = [sep for sep, c in r["raw_contrast"].items() if c is None]
    if missing:
        contrast.append(f"not available at {', '.join(missing)} λ/D")
    parts.append("raw contrast " + ", ".join(contrast))
    if "eta" in r:
        parts.append("η " + ("not defined (the oracle gains nothing over the best classical controller)"
                             if r["eta"] is None else _eta_text(r["eta"]) + _spread(r.get("eta_spread"), _eta_text)))
    return f"{name}: " + "; ".join(parts)


def _ratios_lines(ratios: dict) -> list[str]:
    """The ``ratios`` of a scenario's verdict in words: every predictor, then the oracle, then how fitting error was
    estimated."""
    if ratios.get("over") is None or not (ratios["predictors"] or ratios["oracle"]):
        return []
    where = "over the pupil" if ratios["variance_over"] == "pupil" else "at the actuators"
    lines = [f"Every predictor against the best classical controller, {ratios['over']} (its number over the "
             f"predictor's: above 1 the predictor wins; variance is the median RMS squared {where}):"]
    lines += [f"  - {_predictor_ratio_text(name, r, ratios['fitting_nm'])}." for name, r in ratios["predictors"].items()]
    oracle = ratios["oracle"]
    if oracle is not None:
        lines.append(f"  - Oracle {_predictor_ratio_text(oracle['name'], oracle, ratios['fitting_nm'])}. It "
                     f"{oracle['knowledge']}. η is the share of its variance gain a predictor reaches, "
                     "(σ²_best classical − σ²_predictor) / (σ²_best classical − σ²_oracle).")
    if ratios["fitting_nm"] is not None:
        lines.append(f"  - How the after-fitting ratio is made: {ratios['after_fitting_how']}.")
    return lines


def dm_gain_interval_text(interval) -> str:
    """``0.949 to 1.07``: a stable DM-gain interval (a lower bound at or below 0 reads 0, no upper bound ∞)."""
    low, high = interval
    return f"{max(low or 0.0, 0.0) + 0.0:.3g} to {'∞' if high is None else f'{high:.3g}'}"


def unstable_text(dm_gain: float | None) -> str:
    """What an unstable linear loop means, in words: no stable DM-gain interval contains the plant's DM gain."""
    at = "" if dm_gain is None else f", {dm_gain:g}"
    return f"unstable at this plant (no stable DM-gain interval contains its DM gain{at})"


def _contender(entry: dict) -> str:
    """``integrator (best gain 0.953)`` or ``ol_eof``: a contender's name with how it was set up."""
    if "tuned_setting" in entry:
        setting = ", ".join(f"{k.replace('_', ' ')} {v:g}" if isinstance(v, (int, float)) else f"{k} {v}"
                            for k, v in entry["tuned_setting"].items())
        return f"{entry['name']} (best {setting})"
    if "gain" not in entry:
        return entry["name"]
    how = "best gain" if entry["gain_scanned"] else "fixed gain, not scanned:"
    return f"{entry['name']} ({how} {entry['gain']:g})"


def _ratio_text(against: dict) -> str:
    rms, variance = against["rms_ratio"], against["variance_ratio"]
    if rms >= 1:
        return f"{_times(variance)} in variance, {_times(rms)} in RMS"
    return f"the predictor loses: {_times(1 / variance)} higher in variance, {_times(1 / rms)} in RMS"


def _stability_text(entry: dict, dm_gain: float | None) -> str:
    stability = entry["stability"]
    if stability is None:
        return (f"{entry['name']}: not known (no linear analysis: no linear model, or evaluation.analytic_stability: "
                "false; no simulated margins)")
    if not stability["stable"]:
        return f"{entry['name']}: {unstable_text(dm_gain)} ({stability['source']})"
    interval = stability["dm_gain_interval"]
    high = "beyond 8" if stability["source"] == "simulation" and interval[1] is None else None
    text = (f"{interval[0]:.3g} to {high}" if high else dm_gain_interval_text(interval))
    text = f"{entry['name']}: {text} ({stability['source']})"
    if stability.get("optical_gain") is not None:
        text += f"; {_optical_gain_text(stability['optical_gain'])}"
    if entry.get("near_instability"):
        close = "close to its critical gain" if "gain" in entry else "close to instability"
        text += (f": {close} (gain margin {stability['gain_margin_db']:.2g} dB, delay margin "
                 f"{stability['delay_margin_frames']:.2g} frame)")
    elif stability.get("gain_margin_db") is not None and "gain" in entry:
        text += (f" (gain margin {stability['gain_margin_db']:.2g} dB, delay margin "
                 f"{stability['delay_margin_frames']:.2g} frame)")
    return text


def _optical_gain_text(og: dict) -> str:
    """``optical gain 0.2 to 1.6 (the pyramid's about a flat wavefront is 1)``: a pyramid's stable optical gains."""
    if "compensation_range" not in og:
        return (f"optical gain {dm_gain_interval_text(og['interval'])} (uncompensated: relative to the pyramid's "
                "response about a flat wavefront)")
    low, high = og["compensation_range"]
    return (f"optical gain {dm_gain_interval_text(og['relative_interval'])} times the gain the compensation divides "
            f"each mode by ({low:.3g} to {high:.3g}; at their mean {og['assumed']:.3g}: "
            f"{dm_gain_interval_text(og['interval'])})")


def _training_text(entry: dict, dm_gain: float | None) -> str | None:
    training = entry.get("training")
    if training is None:
        return None
    if training != "retrained in each scenario":
        return f"{entry['name']} was {training}."
    nominal = entry.get("nominal_filter_here", {})
    if not nominal.get("analysed"):
        reason = nominal.get("reason", "not analysed")
        if reason == "this is the nominal scenario":
            return f"{entry['name']} is retrained in each scenario; this is the nominal one."
        return (f"{entry['name']} was retrained in this scenario; whether the nominal filter would be stable here "
                f"is not analysed ({reason}).")
    if nominal["stable"]:
        return (f"{entry['name']} was retrained in this scenario; the nominal filter would be stable here too "
                f"(DM gain {dm_gain_interval_text(nominal['dm_gain_interval'])}, linear analysis).")
    return (f"{entry['name']} was retrained in this scenario; the nominal filter would be "
            f"{unstable_text(dm_gain)} (linear analysis).")


def _spread_text(entries: list[dict], realisations: int) -> str | None:
    if realisations <= 1:
        return None
    parts = [f"{e['name']} {_nm(e['realisations']['median_nm'])} ({e['realisations']['min_nm']:.3g} to "
             f"{e['realisations']['max_nm']:.3g})" for e in entries if e.get("realisations")]
    return (f"Spread over {realisations} realisations (median of their medians, least to greatest): "
            + "; ".join(parts) + ".") if parts else None


def _scenario_lines(scenario: str, v: dict, realisations: int) -> list[str]:
    """The verdict of one scenario, a bullet per statement."""
    predictor, classical, integrator = v["best_predictor"], v["best_classical"], v["best_gain_integrator"]
    lines = []
    if predictor is None:
        lines.append("No predictor held the loop: no verdict on prediction.")
    if classical is None:
        lines.append("No classical controller held the loop.")
    if predictor is not None and classical is not None:
        lines.append(f"Best predictor {predictor['name']} {_nm(predictor['median_rms_nm'])} against the best classical "
                     f"controller, {_contender(classical)}, {_nm(classical['median_rms_nm'])}: "
                     f"{_ratio_text(v['against_best_classical'])}.")
    if predictor is not None and integrator is not None:
        if classical is not None and integrator["name"] == classical["name"]:
            lines.append("The best classical controller is the best-gain integrator."
                         if integrator["gain_scanned"] else
                         "The best classical controller is the integrator, whose gain was not scanned (set `gains` "
                         "for a best-gain integrator).")
        else:
            kind = "the best-gain integrator" if integrator["gain_scanned"] else "the integrator (gain not scanned)"
            lines.append(f"Against {kind}, {_contender(integrator)}, {_nm(integrator['median_rms_nm'])}: "
                         f"{_ratio_text(v['against_best_gain_integrator'])}.")
    elif integrator is None:
        lines.append("No integrator held the loop.")
    shown = [e for e in (predictor, classical, integrator) if e is not None]
    shown = list({e["name"]: e for e in shown}.values())
    contrast = [f"{e['name']} {e['raw_contrast_3_lod']:.2g}" for e in shown if e["raw_contrast_3_lod"] is not None]
    missing = [e["name"] for e in shown if e["raw_contrast_3_lod"] is None]
    if contrast or missing:
        lines.append("Raw contrast at 3 λ/D: " + (", ".join(contrast) if contrast else "")
                     + ("; " if contrast and missing else "")
                     + (f"not available for {', '.join(missing)} (separation outside the grid)" if missing else "")
                     + ".")
    dm_gain = v.get("dm_gain")
    if shown:
        at = "" if dm_gain is None else f" (this plant: DM gain {dm_gain:g})"
        lines.append(f"Stable DM-gain intervals{at}: " + "; ".join(_stability_text(e, dm_gain) for e in shown) + ".")
    if predictor is not None:
        training = _training_text(predictor, dm_gain)
        if training:
            lines.append(training)
    for key, what in (("diverged", "diverged"), ("diverging", "kept diverging")):
        if v[key]:
            lines.append(f"{', '.join(v[key])} {what}: never counted as best.")
    spread = _spread_text(shown, realisations)
    if spread:
        lines.append(spread)
    ratios = _ratios_lines(v.get("ratios") or {})
    if ratios:
        lines.append("\n".join(ratios))
    return [f"**{scenario}**"] + [f"- {line}" for line in lines]


def verdict_markdown(verdict: dict) -> str:
    """The ``## Verdict`` section of ``results.md`` from ``metrics.json``'s ``verdict``."""
    realisations = verdict["realisations"]
    head = ("1 realisation of the test turbulence per run: no spread; set evaluation.realisations for one."
            if realisations <= 1 else
            f"{realisations} realisations of the test turbulence per run (each its own seed); the headline numbers "
            "pool their frames, the spread is over the realisations' own medians.")
    blocks = ["## Verdict", "", "Ratios are the best classical controller's median RMS (or variance, RMS²) over the "
              "best predictor's: above 1 the predictor wins. " + head, ""]
    for scenario, v in verdict["scenarios"].items():
        blocks += _scenario_lines(scenario, v, realisations) + [""]
    return "\n".join(blocks)


__all__ = ["dm_gain_interval_text", "unstable_text", "verdict_markdown"]
