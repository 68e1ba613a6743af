"""What :func:`eofnn.studies.antialias.run_antialias` concludes: every predictor's ratios over a classical controller
(plain variance, RMS, variance after fitting, raw contrast against the classical controller best in contrast at each
separation), the oracle's ceiling and each predictor's share of it (``eta``), and ``results.md``.
"""

from __future__ import annotations

import math

from eofnn.evaluation.verdict import eta
from eofnn.studies.loop_scans import CLASSICAL
from eofnn.studies.report import psd_bands_markdown

#: The oracle's name among the contenders: a ceiling, never a contender (never the best predictor, never deployed).
ORACLE = "oracle"


def best_in_contrast(results: dict, separations: tuple[float, ...]) -> dict[str, str | None]:
    """Per separation (``"3"``), the classical controller of least mean raw contrast there (``None`` where none held
    the loop with a contrast): the baseline a contrast gain is taken against, not the one best in variance."""
    out = {}
    for s in (f"{s:g}" for s in separations):
        have = [n for n in CLASSICAL if n in results and (results[n]["mean_contrast"] or {}).get(s) is not None]
        out[s] = min(have, key=lambda n: results[n]["mean_contrast"][s]) if have else None
    return out


def gains(results: dict, fitting: list[float], separations: tuple[float, ...], against: str,
          contrast_against: dict[str, str | None] | None = None) -> dict:
    """Each predictor against the classical controller ``against``: the plain variance (median RMS squared, summed
    over realisations) and RMS ratios, the variance after fitting (each realisation's fitting error subtracted in
    quadrature, summed over realisations) and mean raw contrast, as classical over predictor (above 1: the predictor
    is better), and the paired RMS differences. ``contrast_against``: per separation, the controller the contrast is
    compared with (:func:`best_in_contrast`; said in ``contrast_against``); unset, ``against``."""
    out = {}
    for name in (n for n in results if n not in CLASSICAL):
        base, mine = results[against], results[name]
        if mine["mean_of_realisations_nm"] is None or base["mean_of_realisations_nm"] is None:  # one diverged
            out[name] = None
            continue
        var = [sum(r * r - f * f for r, f in zip(run["realisations_median_rms_nm"], fitting, strict=True))
               for run in (base, mine)]
        plain = [sum(r * r for r in run["realisations_median_rms_nm"]) for run in (base, mine)]
        contrast, used = {}, {}
        for s in (f"{s:g}" for s in separations):
            other = results.get((contrast_against or {}).get(s) or against)
            if other is None or other["mean_contrast"] is None or other["mean_contrast"].get(s) is None:
                continue
            contrast[s] = other["mean_contrast"][s] / mine["mean_contrast"][s]
            used[s] = (contrast_against or {}).get(s) or against
        out[name] = {"variance": plain[0] / plain[1],
                     "rms": base["mean_of_realisations_nm"] / mine["mean_of_realisations_nm"],
                     "variance_after_fitting": var[0] / var[1],
                     "contrast": contrast, "contrast_against": used,
                     "paired_difference_nm": [a - b for a, b in zip(base["realisations_median_rms_nm"],
                                                                    mine["realisations_median_rms_nm"], strict=True)]}
    return out


def etas(results: dict, against: str) -> dict:
    """Each predictor's share of the oracle's variance gain over the classical controller ``against``, as eofnn's
    verdict computes it (:func:`eofnn.evaluation.verdict.eta`): ``(var_against - var_predictor) / (var_against -
    var_oracle)``, the variances the median RMS squared summed over the scored realisations (the plain variance ratio's),
    with the same share realisation by realisation (``per_realisation``). ``None`` where one diverged; ``eta`` is
    ``None`` where the oracle gains nothing. The oracle itself is not rated."""
    oracle, base = results.get(ORACLE), results[against]
    out = {}
    for name in (n for n in results if n not in CLASSICAL and n != ORACLE):
        runs = (base, results[name], oracle)
        if oracle is None or any(run["mean_of_realisations_nm"] is None for run in runs):
            out[name] = None
            continue
        b, m, o = (math.sqrt(sum(r * r for r in run["realisations_median_rms_nm"])) for run in runs)
        out[name] = {"eta": eta(b, m, o), "against": against,
                     "per_realisation": [eta(*each) for each in zip(*(run["realisations_median_rms_nm"] for run in runs),
                                                                    strict=True)]}
    return out


def antialias_markdown(metrics: dict) -> str:
    """``results.md`` of :func:`run_antialias`: per contender the residual per realisation, its mean and the raw
    contrast, then the gains over the integrator."""
    def nm(value):
        return "diverged" if value is None else f"{value:.1f}"

    seps = [f"{s:g}" for s in metrics["config"]["separations_lod"]]
    fit = metrics["fitting_error_nm"]
    sensor = " (modulated pyramid)" if metrics["simulator"].get("sensor") == "pyramid" else ""
    lines = [f"# Anti-aliasing EOF inside {metrics['simulator']['simulator']}{sensor}", "", f"`{metrics.get('command', '')}`", "",
             f"Fitting error per realisation: {', '.join(f'{v:.1f}' for v in fit)} nm. Integrator gain "
             f"{metrics['integrator_scan']['gain']} (scanned); deployed by the guard: {metrics['guard']['deployed']}.",
             "", "| contender | residual per realisation (nm) | mean (nm) | "
             + " | ".join(f"raw contrast at {s} λ/D" for s in seps) + " |", "|---|---|---|" + "---|" * len(seps)]
    for name, run in metrics["contenders"].items():
        contrast = run["mean_contrast"] or {}
        lines.append(f"| {name} | {', '.join(nm(v) for v in run['realisations_median_rms_nm'])} | "
                     f"{nm(run['mean_of_realisations_nm'])} | "
                     + " | ".join("" if contrast.get(s) is None else f"{contrast[s]:.2e}" for s in seps) + " |")
    lines += psd_bands_markdown(metrics)
    lqg, pfc = metrics["lqg_scan"], metrics.get("pfc_scan")
    winds = "" if not pfc else f" PFC: alpha {pfc.get('alpha', 0.9999):g}, {pfc['aliases']} ring(s) of aliases, " \
        f"{pfc.get('noise_covariance', 'white')} noise " \
        f"(scan: {pfc['scan']}), layers " + ", ".join(
        f"{lay['speed_mps']:.1f} m/s at {lay['direction_deg']:.0f}° ({lay['weight']:.0%})"
        for lay in pfc["identified"]["layers"] or []) + " identified from the telemetry."
    modal = metrics.get("modal_scan")
    gains_line = "" if not modal else f" Modal integrator (optimised gains): gain margin {modal['gain_margin']:g} " \
        f"(scan: {modal['scan']}), gains {modal['info']['gains_quantiles_0_10_50_90_100']} (quantiles 0-10-50-90-100%)."
    lines += ["", f"LQG: AR order {lqg['ar_order']}{_noise_scale(lqg)} (scan: {lqg['scan']}).{winds}{gains_line} "
                  f"Best classical controller, chosen on the scan realisation: {metrics['best_classical']}."]
    oracle = metrics.get("fits", {}).get(ORACLE)
    if oracle is not None:
        lines += ["", f"Oracle ({ORACLE}): {oracle['knowledge']}. {oracle['history_length']} taps, neighbourhood radius "
                      f"{oracle['radius']:g} pitches, {oracle['sequences']} recordings of "
                      f"{metrics['config']['train_frames']} frames ({oracle['val_frames']} of each held out for its "
                      f"ridge alpha, {oracle['alpha']}). η: the share of the oracle's variance gain over a classical "
                      "controller that a predictor reaches, (σ² classical − σ² predictor) / (σ² classical − σ² oracle), "
                      "σ² the median RMS squared summed over the scored realisations."]
    best, scored = metrics["best_classical"], metrics.get("best_classical_on_scored")
    tables = [("gains", "integrator", None)]
    if best != "integrator":
        tables.append(("gains_over_best_classical", best, "eta"))
    elif metrics.get("eta") is not None:
        tables[0] = ("gains", "integrator", "eta")
    if scored is not None and scored != best:
        lines += ["", f"The classical controller of least residual on the scored realisations is {scored}, not {best} "
                      "(chosen on the scan realisation): against it too."]
        tables.append(("gains_over_best_classical_on_scored", scored, "eta_over_best_classical_on_scored"))
    for key, against, eta_key in tables:
        etas_here = metrics.get(eta_key) or {} if eta_key else {}
        lines += ["", f"Against the {against} (its residual over the predictor's: above 1, the predictor is better):",
                  "", "| predictor | variance gain | RMS gain | variance gain after fitting (fitting error of each "
                  "realisation subtracted in quadrature) | contrast gain (against the classical controller best in "
                  "contrast at each separation) | paired differences (nm) | η (per realisation) |",
                  "|---|---|---|---|---|---|---|"]
        for name, gain in metrics[key].items():
            if gain is None:
                lines.append(f"| {name} | diverged | | | | | |")
                continue
            against = gain.get("contrast_against", {})
            lines.append(f"| {name} | {gain.get('variance', math.nan):.2f}x | {gain.get('rms', math.nan):.2f}x | "
                         f"{gain['variance_after_fitting']:.2f}x | "
                         + ", ".join(f"{v:.2f}x at {s}" + (f" ({against[s]})" if s in against else "")
                                     for s, v in gain["contrast"].items()) + " | "
                         + ", ".join(f"{v:+.1f}" for v in gain["paired_difference_nm"]) + " | "
                         + _eta_cell(name, etas_here) + " |")
    return "\n".join(lines) + "\n"


def _eta_cell(name: str, etas_here: dict) -> str:
    """η of ``name`` and its values per realisation (``oracle``: the ceiling itself; empty: no oracle ran)."""
    if name == ORACLE:
        return "1 (the ceiling)" if etas_here else ""
    entry = etas_here.get(name)
    if entry is None or entry["eta"] is None:
        return "" if entry is None else "undefined (the oracle gains nothing)"
    return f"{entry['eta']:.2f} (" + ", ".join("n/a" if v is None else f"{v:.2f}" for v in entry["per_realisation"]) + ")"


def _noise_scale(lqg: dict) -> str:
    """`` (the random walk), noise variance x 0.5``: what an LQG's scan chose besides its AR order (nothing for a run made
    before the noise scale was scanned)."""
    walk = " (the random walk)" if lqg["ar_order"] == 0 else ""
    return walk + ("" if "noise_scale" not in lqg else f", noise variance x {lqg['noise_scale']:g}")
