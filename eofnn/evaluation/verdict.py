"""The verdict of a comparison, per scenario: the best predictor against the best classical controller and against
the best-gain integrator, with the numbers a reader needs to believe it (ratios of median RMS and of variance, raw
contrast at 3 lambda/D, stable DM-gain intervals, how close the integrator sits to its critical gain, where each
predictor was trained, and the spread over turbulence realisations).

The verdict is a JSON-ready dict (``metrics.json``: ``verdict``); :mod:`eofnn.reporting.verdict` writes it as the
first section of ``results.md``. Every number in it comes from the :class:`ExperimentResult`; nothing is recomputed
except, where asked, the analytic stability of the nominal filter in another scenario's plant.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable, Mapping
from typing import Any

from eofnn.control.registry import NEEDS_PREDICTOR
from eofnn.evaluation.metrics import LoopMetrics
from eofnn.evaluation.results import ExperimentResult

#: Controllers that are references, not contenders: no correction, and perfect correction from the simulator's truth
#: (not realisable on a telescope). Every other non-predictor controller counts as classical.
REFERENCES = ("uncorrected", "pseudo_integrator")

#: A linear controller is said to sit close to instability (an integrator: to its critical gain) below these
#: margins (either one).
NEAR_CRITICAL_GAIN_MARGIN_DB = 1.0
NEAR_CRITICAL_DELAY_MARGIN_FRAMES = 0.5

#: The separation (lambda/D) whose raw contrast the verdict quotes (a key of ``raw_contrast`` in ``metrics.json``).
CONTRAST_SEPARATION = "3"


def contender_roles(predictors: Mapping[str, Any]) -> dict[str, dict]:
    """What each controller is in a verdict, from its :class:`~eofnn.evaluation.config.PredictorConfig`:
    ``{"role": "predictor" | "classical" | "reference", "best_gain": bool, "training": ...}``.

    ``training`` is ``"retrained in each scenario"`` for a predictor trained by the experiment without ``train_in``
    (:meth:`~eofnn.evaluation.experiment.Experiment.predictor` trains it in every scenario it is evaluated in),
    ``"trained in <scenario>"`` with ``train_in``, ``"from a checkpoint"`` for a checkpoint, ``None`` otherwise.
    ``best_gain`` marks an integrator whose gain is chosen per scenario (``gains``).
    """
    roles = {}
    for name, cfg in predictors.items():
        if cfg.controller in NEEDS_PREDICTOR:
            role = "predictor"
            training = ("from a checkpoint" if cfg.checkpoint is not None else
                        f"trained in {cfg.train_in}" if cfg.train_in else "retrained in each scenario")
            if cfg.checkpoint is None and cfg.train_in and cfg.data.plant_range:
                training += " over " + ", ".join(f"{field} {low:g} to {high:g}"
                                                 for field, (low, high) in cfg.data.plant_range.items())
        else:
            role = "reference" if cfg.controller in REFERENCES else "classical"
            training = None
        roles[name] = {"role": role, "controller": cfg.controller, "training": training,
                       "best_gain": cfg.controller == "integrator" and cfg.gains is not None,
                       "gain": None if cfg.controller != "integrator" else cfg.gain}
    return roles


def _spread(m: LoopMetrics) -> dict | None:
    """The median RMS of each realisation, and their median, least and greatest (nm)."""
    medians = list(m.realisation_median_rms_nm)
    if not medians:
        return None
    return {"medians_nm": medians, "median_nm": statistics.median(medians), "min_nm": min(medians),
            "max_nm": max(medians)}


def _stability(result: ExperimentResult, scenario: str, name: str) -> dict | None:
    """The stable DM-gain interval of ``name`` in ``scenario``: analytic (linear), by simulation, or ``None``."""
    analytic = result.stability.get(scenario, {}).get(name)
    if analytic is not None:
        return {"source": "linear analysis", "stable": bool(analytic["stable"]),
                "dm_gain_interval": analytic["dm_gain_interval"] if analytic["stable"] else None,
                "gain_margin_db": analytic.get("gain_margin_db"),
                "delay_margin_frames": analytic.get("delay_margin_frames")}
    simulated = result.simulated_stability.get(scenario, {}).get(name)
    if simulated is not None:
        interval = simulated["dm_gain_interval"]
        return {"source": "simulation", "stable": interval is not None, "dm_gain_interval": interval,
                "tolerance": simulated.get("tolerance")}
    return None


def _entry(result: ExperimentResult, scenario: str, name: str, role: dict) -> dict:
    """One contender of a verdict: its numbers in ``scenario``."""
    m = result.metrics[scenario][name]
    entry = {"name": name, "median_rms_nm": m.median_rms_nm,
             "raw_contrast_3_lod": (m.contrast_at or {}).get(CONTRAST_SEPARATION),
             "realisations": _spread(m), "stability": _stability(result, scenario, name)}
    if role["training"] is not None:
        entry["training"] = role["training"]
    if role["controller"] == "integrator":
        scan = result.integrator_gains.get(scenario, {}).get(name)
        entry["gain"] = scan["gain"] if scan is not None else role["gain"]
        entry["gain_scanned"] = scan is not None
        if scan is not None and "critical_gain" in scan:
            entry["critical_gain"] = scan["critical_gain"]
    tuned = result.classical_settings.get(scenario, {}).get(name)
    if tuned is not None:  # its settings (order, smoothing, AR order) were scanned on a stream of its own
        entry["tuned_setting"] = {k: v for k, v in tuned.items() if k not in ("median_rms_nm", "scanned")}
    stability = entry["stability"]
    if stability is not None and stability["source"] == "linear analysis" and stability["stable"]:
        # Thin margins matter for any linear controller; for an integrator they mean a gain near its critical one.
        margin_db, delay = stability["gain_margin_db"], stability["delay_margin_frames"]
        entry["near_instability"] = bool(
            (margin_db is not None and margin_db < NEAR_CRITICAL_GAIN_MARGIN_DB)
            or (delay is not None and delay < NEAR_CRITICAL_DELAY_MARGIN_FRAMES))
    return entry


def _best(entries: list[dict]) -> dict | None:
    """The entry of least median RMS (``None`` when there is none)."""
    return min(entries, key=lambda e: e["median_rms_nm"]) if entries else None


def _against(predictor: dict | None, other: dict | None) -> dict | None:
    """How many times lower the predictor's median RMS and variance (RMS squared) are than ``other``'s (below 1:
    the predictor loses)."""
    if predictor is None or other is None or not predictor["median_rms_nm"]:
        return None
    ratio = other["median_rms_nm"] / predictor["median_rms_nm"]
    return {"name": other["name"], "rms_ratio": ratio, "variance_ratio": ratio ** 2}


def build_verdict(result: ExperimentResult, roles: Mapping[str, dict], realisations: int,
                  nominal_filter_stability: Callable[[str, str], dict | None] | None = None) -> dict:
    """The verdict of ``result`` per scenario (see the module's docstring).

    Parameters
    ----------
    result : ExperimentResult
        The comparison.
    roles : mapping
        :func:`contender_roles` of its controllers.
    realisations : int
        Turbulence realisations each run was scored on (``evaluation.realisations``).
    nominal_filter_stability : callable, optional
        ``(name, scenario) -> summary or None``: the analytic stability, in ``scenario``'s plant, of the filter
        ``name`` trained in the first scenario (for a predictor retrained in each scenario); ``None`` where not
        analysed. Unset: not analysed anywhere.

    Returns
    -------
    dict
        ``{"realisations": n, "scenarios": {scenario: {"best_predictor", "best_classical", "best_gain_integrator",
        "against_best_classical", "against_best_gain_integrator", "diverged", "diverging", "nominal_scenario",
        "dm_gain"}}}``; a contender is ``None`` when none of its kind held (a diverged or diverging run is never
        best: it is listed in ``diverged`` or ``diverging`` instead).
    """
    scenarios = list(result.metrics)
    out = {"realisations": realisations, "scenarios": {}}
    for scenario, preds in result.metrics.items():
        held = {role: [] for role in ("predictor", "classical", "reference")}
        diverged, diverging = [], []
        for name, m in preds.items():
            if m.diverged or m.median_rms_nm is None:
                diverged.append(name)
            elif m.diverging:
                diverging.append(name)
            else:
                held[roles[name]["role"]].append(_entry(result, scenario, name, roles[name]))
        best_predictor = _best(held["predictor"])
        best_classical = _best(held["classical"])
        scanned = [e for e in held["classical"] if roles[e["name"]]["best_gain"]]
        # Without a gain scan the best fixed-gain integrator stands in, said as such (gain_scanned: false).
        integrators = scanned or [e for e in held["classical"] if roles[e["name"]]["controller"] == "integrator"]
        best_integrator = _best(integrators)
        if best_predictor is not None and best_predictor.get("training") == "retrained in each scenario":
            if scenario == scenarios[0]:
                best_predictor["nominal_filter_here"] = {"analysed": False, "reason": "this is the nominal scenario"}
            elif nominal_filter_stability is None:
                best_predictor["nominal_filter_here"] = {"analysed": False, "reason": "no analysis asked for"}
            else:
                summary = nominal_filter_stability(best_predictor["name"], scenario)
                best_predictor["nominal_filter_here"] = (
                    {"analysed": False, "reason": "no linear model, or too large to analyse"} if summary is None else
                    {"analysed": True, "stable": bool(summary["stable"]),
                     "dm_gain_interval": summary["dm_gain_interval"] if summary["stable"] else None})
        out["scenarios"][scenario] = {
            "nominal_scenario": scenarios[0],
            "dm_gain": result.scenario_dm_gains.get(scenario),
            "best_predictor": best_predictor,
            "best_classical": best_classical,
            "best_gain_integrator": best_integrator,
            "against_best_classical": _against(best_predictor, best_classical),
            "against_best_gain_integrator": _against(best_predictor, best_integrator),
            "diverged": diverged,
            "diverging": diverging,
        }
    return out


__all__ = ["build_verdict", "contender_roles"]
