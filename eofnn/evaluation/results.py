"""What an experiment produced: metrics by scenario and predictor, and the files that keep them."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eofnn.control.config import RANDOM_WALK
from eofnn.evaluation.metrics import LoopMetrics


@dataclass
class ExperimentResult:
    """Metrics by scenario and predictor, where the checkpoints went (relative to the output folder), timings."""

    metrics: dict[str, dict[str, LoopMetrics]]
    checkpoints: dict[str, str] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    #: Analytic stability of the linear controllers: scenario -> controller -> summary (stable, DM gain interval...).
    stability: dict[str, dict[str, dict]] = field(default_factory=dict)
    #: Best-gain integrators: scenario -> controller -> {"gain": chosen, "scanned": {gain: median RMS or None}}.
    integrator_gains: dict[str, dict[str, dict]] = field(default_factory=dict)
    #: Ridge alphas chosen on validation data: training scenario -> controller -> {"alpha", "val_loss", "path"}.
    ridge_alphas: dict[str, dict[str, dict]] = field(default_factory=dict)
    #: Budgeted searches of SGD-trained networks: training scenario -> controller -> {"trials", "chosen", "budget"}.
    searches: dict[str, dict[str, dict]] = field(default_factory=dict)
    #: DM-gain intervals of controllers without a linear model, by simulation: scenario -> controller -> result.
    simulated_stability: dict[str, dict[str, dict]] = field(default_factory=dict)
    #: Classical models built from telemetry: scenario -> controller -> what was identified (modes, gains, AR(2)).
    classical_models: dict[str, dict[str, dict]] = field(default_factory=dict)
    #: The process's peak resident memory (bytes) after each scenario/controller step: the step that raised it is the
    #: one that needed it (``None`` where the platform does not say).
    peak_memory_bytes: dict[str, int | None] = field(default_factory=dict)
    #: The plant's DM gain in each scenario (what a stable DM-gain interval must contain): scenario -> gain.
    scenario_dm_gains: dict[str, float] = field(default_factory=dict)
    #: The verdict per scenario (:func:`eofnn.evaluation.verdict.build_verdict`): best predictor against the best
    #: classical controller and the best-gain integrator; ``None`` when not built (then not in ``metrics.json``).
    verdict: dict | None = None
    #: The gain every integrator ran at: scenario -> controller -> {"gain": loop gain (dimensionless), "scanned":
    #: whether it was chosen by a best-gain scan (``integrator_gains`` has the scan) or fixed by the config}.
    integrator_gain_used: dict[str, dict[str, dict]] = field(default_factory=dict)
    #: Classical controllers whose settings were chosen on a stream of their own (the extrapolator's ``order`` and
    #: ``smoothing``, the LQG's ``ar_order``): scenario -> controller -> {the chosen setting's fields, "median_rms_nm"
    #: (of the choice, on that stream), "scanned": [every setting tried with its median_rms_nm, None if it diverged]}.
    classical_settings: dict[str, dict[str, dict]] = field(default_factory=dict)
    #: Fallbacks to the best-gain integrator (``fallback:``): scenario -> controller -> {"deployed": predictor,
    #: composite or integrator, "why", "integrator_gain", per mode "n_modes", "predictor_modes", "fallen_back":
    #: {"worse": [modes], "within_scatter": [modes]}, "per_mode" and "whole" gains with their scatter (nm²), ...}.
    fallbacks: dict[str, dict[str, dict]] = field(default_factory=dict)

    def to_json(self) -> dict:
        verdict = {} if self.verdict is None else {"verdict": self.verdict}
        spread = {s: {p: m.realisation_median_rms_nm for p, m in preds.items() if len(m.realisation_median_rms_nm) > 1}
                  for s, preds in self.metrics.items()}
        if any(spread.values()):  # every contender's median per realisation (evaluation.realisations > 1)
            verdict["realisation_median_rms_nm"] = spread
        return {**verdict,
            "scenarios": {s: {p: m.summary() for p, m in preds.items()} for s, preds in self.metrics.items()},
            "stability": self.stability,
            "integrator_gains": self.integrator_gains,
            "integrator_gain_used": self.integrator_gain_used,
            "classical_settings": self.classical_settings,
            **({"fallback": self.fallbacks} if self.fallbacks else {}),
            "ridge_alphas": self.ridge_alphas,
            "searches": self.searches,
            "simulated_stability": self.simulated_stability,
            "classical_models": self.classical_models,
            "raw_contrast": {s: {p: m.contrast_at for p, m in preds.items() if m.contrast_at}
                             for s, preds in self.metrics.items()},
            "checkpoints": self.checkpoints,
            "timings_s": self.timings_s,
            "peak_memory_bytes": self.peak_memory_bytes,
        }


#: How a setting of a classical controller reads in a line (``results.md``, progress).
SETTING_LABELS = {"order": "order {}", "smoothing": "smoothing {}", "ar_order": "AR({})", "pfc.alpha": "alpha {}",
                  "noise_scale": "noise x {:g}"}
#: The value of a setting's later field that goes unsaid when every setting tried has it (0 unless listed).
SETTING_DEFAULTS = {"noise_scale": 1.0}


def describe_setting_scan(scan: dict) -> str:
    """``order 2 chosen (2.06 nm) over order 1 (3.86), order 0 (5.1)``: the choice, then the others from best to
    worst (diverged last). The first field of a setting is always named; another (``smoothing``, ``noise_scale``)
    when some setting tried has it other than its default (:data:`SETTING_DEFAULTS`)."""
    entries = scan["scanned"]
    fields = [key for key in entries[0] if key != "median_rms_nm"]
    shown = [key for i, key in enumerate(fields)
             if i == 0 or any(e[key] != SETTING_DEFAULTS.get(key, 0) for e in entries)]

    def name(entry: dict) -> str:
        return ", ".join("random walk" if key == "ar_order" and entry[key] == RANDOM_WALK else
                         SETTING_LABELS.get(key, key + " {}").format(entry[key]) for key in shown)

    chosen = next(e for e in entries if all(e[key] == scan[key] for key in fields))
    others = sorted((e for e in entries if e is not chosen),
                    key=lambda e: (e["median_rms_nm"] is None, e["median_rms_nm"] or 0.0))
    text = f"{name(chosen)} chosen ({chosen['median_rms_nm']:.3g} nm)"
    if others:
        text += " over " + ", ".join(f"{name(e)} ("
                                     + ("diverged" if e["median_rms_nm"] is None else f"{e['median_rms_nm']:.3g}")
                                     + ")" for e in others)
    return text


def write_metrics(result: ExperimentResult, path: Path) -> None:
    """``metrics.json``: every scalar metric, the checkpoints and the timings."""
    path.write_text(json.dumps(result.to_json(), indent=2))


def save_timeseries(result: ExperimentResult, path: Path) -> None:
    """Per-frame RMS and PSDs of every run, for re-plotting without re-running."""
    data = {}
    for s, preds in result.metrics.items():
        for p, m in preds.items():
            data[f"{s}/{p}/rms_nm"] = np.asarray(m.rms_nm, dtype=np.float64)
            data[f"{s}/{p}/psd_freq_hz"] = np.asarray(m.psd_freq_hz, dtype=np.float64)
            data[f"{s}/{p}/psd_nm2_per_hz"] = np.asarray(m.psd_nm2_per_hz, dtype=np.float64)
            data[f"{s}/{p}/contrast_separation_lod"] = np.asarray(m.contrast_separation_lod, dtype=np.float64)
            data[f"{s}/{p}/raw_contrast"] = np.asarray(m.contrast, dtype=np.float64)
    np.savez_compressed(path, **data)


def describe_run(m: LoopMetrics, margins: dict | None, scenario=None) -> str:
    """One progress line: the median RMS (or where it diverged, or that it is diverging) and, for a linear
    controller, its analytic DM gain margin (with the growth rate its largest root implies when it is unstable).

    The margins come from the linear loop model (DM gain, delay, misregistration; no saturation or other
    nonlinearity): the line says "linear analysis", so a nonlinear plant diverging where it says stable reads right.
    """
    if m.diverged:
        text = f"median RMS diverged at frame {m.diverged_frame}"
    else:
        text = f"median RMS {m.median_rms_nm:.4g} nm"
        if m.diverging:
            text += f", diverging (amplitude grows {m.growth['growth_rate_per_s']:+.3g}/s)"
    if margins is None:
        return text
    low, high = margins["dm_gain_interval"]
    text += "; linear analysis: " + ("stable" if margins["stable"] else "unstable")
    if margins["stable"] and low is not None and high is not None:
        text += f" for DM gain {max(low, 0.0) + 0.0:.3g} to {high:.3g}"
    elif not margins["stable"] and scenario is not None:
        root = margins["max_root_modulus"]
        text += f" (largest root {root:.5g}: {scenario.frame_rate_hz * math.log(root):+.3g}/s)"
    return text


def by_scenario(per_controller: dict[tuple[str, str], dict]) -> dict[str, dict[str, dict]]:
    """``{(controller, scenario): value}`` regrouped as ``{scenario: {controller: value}}``, as result files hold it."""
    out: dict[str, dict[str, dict]] = {}
    for (name, scenario_name), value in per_controller.items():
        out.setdefault(scenario_name, {})[name] = value
    return out
