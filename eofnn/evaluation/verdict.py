"""The verdict of a comparison, per scenario: the best predictor against the best classical controller and against
the best-gain integrator, with the numbers a reader needs to believe it (ratios of median RMS and of variance, raw
contrast at 3 lambda/D, stable DM-gain intervals, how close the integrator sits to its critical gain, where each
predictor was trained, and the spread over turbulence realisations).

Every predictor's ratios over the best classical controller are stated plainly (``ratios``): the plain variance
ratio first (median RMS squared, over the pupil for a Shack-Hartmann scenario, at the actuators for the zonal
sensor), the RMS ratio, the variance ratio after fitting error (labelled with how the fitting error was estimated),
and raw contrast at 2, 3 and 5 lambda/D against the classical controller that is best *in contrast* at that
separation; each with its spread over the turbulence realisations (ratios paired realisation by realisation: every
run of a realisation sees the same turbulence). Where an oracle ran (``oracle: true``: a predictor that learns from
the simulator's truth, with more reach than any contender: knowledge no telescope has), its own ratio over the best
classical controller and every predictor's ``eta``, the share of the oracle's variance gain it reaches.

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

#: The separations (lambda/D) whose raw contrast every predictor's ``ratios`` compare, each against the classical
#: controller best in contrast there.
RATIO_SEPARATIONS = ("2", "3", "5")

#: How the after-fitting variance ratio's fitting error is estimated (said beside the ratio).
FITTING_ESTIMATE = ("fitting error: the median over the scored frames of the test stream's turbulence of the pupil "
                    "RMS of the true phase minus the DM's least-squares fit of it (no loop), one number for all "
                    "realisations, subtracted in quadrature from each contender's median RMS (a difference of squared "
                    "medians)")


def contender_roles(predictors: Mapping[str, Any]) -> dict[str, dict]:
    """What each controller is in a verdict, from its :class:`~eofnn.evaluation.config.PredictorConfig`:
    ``{"role": "predictor" | "oracle" | "classical" | "reference", "best_gain": bool, "training": ...}``.

    ``oracle`` is a predictor whose config says ``oracle: true``: it learns from the simulator's truth with more reach
    than any contender, a bound for the others, never a contender itself.

    ``training`` is ``"retrained in each scenario"`` for a predictor trained by the experiment without ``train_in``
    (:meth:`~eofnn.evaluation.experiment.Experiment.predictor` trains it in every scenario it is evaluated in),
    ``"trained in <scenario>"`` with ``train_in``, ``"from a checkpoint"`` for a checkpoint, ``None`` otherwise.
    ``best_gain`` marks an integrator whose gain is chosen per scenario (``gains``).
    """
    roles = {}
    for name, cfg in predictors.items():
        if cfg.controller in NEEDS_PREDICTOR:
            role = "oracle" if getattr(cfg, "oracle", False) else "predictor"
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
        out = {"source": "linear analysis", "stable": bool(analytic["stable"]),
               "dm_gain_interval": analytic["dm_gain_interval"] if analytic["stable"] else None,
               "gain_margin_db": analytic.get("gain_margin_db"),
               "delay_margin_frames": analytic.get("delay_margin_frames")}
        if analytic.get("optical_gain") is not None:  # a pyramid: the same interval in optical gain
            out["optical_gain"] = analytic["optical_gain"]
        return out
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


def _paired(best: list[float], mine: list[float], ratio: Callable[[float, float], float | None]) -> dict | None:
    """``ratio(best, mine)`` realisation by realisation, with its median, least and greatest; ``None`` with fewer
    than two realisations (or a different number of them)."""
    if len(best) < 2 or len(best) != len(mine):
        return None
    values = [ratio(b, m) for b, m in zip(best, mine, strict=True)]
    if any(v is None for v in values):
        return {"per_realisation": values, "median": None, "min": None, "max": None}
    return {"per_realisation": values, "median": statistics.median(values), "min": min(values), "max": max(values)}


def _variance_ratio(best: float, mine: float) -> float | None:
    return (best / mine) ** 2 if mine else None


def eta(best: float, mine: float, oracle: float) -> float | None:
    """``(best² - mine²) / (best² - oracle²)`` (RMS in, variances compared); ``None`` when the oracle gains nothing."""
    gain = best * best - oracle * oracle
    return (best * best - mine * mine) / gain if gain > 0 else None


def _fitting(metrics: Mapping[str, LoopMetrics]) -> float | None:
    """The scenario's fitting error (nm, from any contender's error budget: one test stream, one number)."""
    for m in metrics.values():
        if m.error_budget is not None and m.error_budget.get("fitting_nm") is not None:
            return float(m.error_budget["fitting_nm"])
    return None


def _after_fitting(best: float, mine: float, fitting: float) -> float | None:
    mine_left, best_left = mine * mine - fitting * fitting, best * best - fitting * fitting
    return best_left / mine_left if mine_left > 0 else None


def _contrast_ratios(metrics: Mapping[str, LoopMetrics], mine: LoopMetrics, classical: list[str]) -> dict:
    """Raw contrast at :data:`RATIO_SEPARATIONS`: per separation, the classical controller best in contrast there
    (``against``), its contrast over the predictor's (``ratio``, above 1 the predictor wins) and the paired spread."""
    out = {}
    for sep in RATIO_SEPARATIONS:
        have = [name for name in classical if (metrics[name].contrast_at or {}).get(sep) is not None]
        own = (mine.contrast_at or {}).get(sep)
        if not have or own is None:
            out[sep] = None  # beyond the control radius, or no classical controller held the loop
            continue
        best = min(have, key=lambda name: metrics[name].contrast_at[sep])
        theirs = metrics[best].realisation_contrast_at
        spread = _paired([c.get(sep) for c in theirs], [c.get(sep) for c in mine.realisation_contrast_at],
                         lambda b, m: b / m if b is not None and m else None)
        out[sep] = {"against": best, "contrast": own, "against_contrast": metrics[best].contrast_at[sep],
                    "ratio": metrics[best].contrast_at[sep] / own if own else None, "spread": spread}
    return out


def predictor_ratios(metrics: Mapping[str, LoopMetrics], predictors: list[str], classical: list[str],
                     best_classical: str | None, oracle: str | None) -> dict:
    """Every predictor's ratios over the best classical controller (the module's docstring): ``{"over", "variance_over",
    "after_fitting_how", "fitting_nm", "predictors": {name: {...}}, "oracle": {...} or None}``.

    Parameters
    ----------
    metrics : mapping
        The scenario's :class:`LoopMetrics` by controller.
    predictors : list of str
        The predictors that held the loop.
    classical : list of str
        The classical controllers that held the loop (candidates for best in contrast).
    best_classical : str or None
        The classical controller of least median RMS (the variance ratios' reference); ``None``: no ratios.
    oracle : str or None
        The oracle, if one ran and held the loop.
    """
    if best_classical is None:
        return {"over": None, "predictors": {}, "oracle": None}
    base = metrics[best_classical]
    fitting = _fitting(metrics)
    over = "pupil" if base.residual_over == "pupil" else "actuators"
    oracle_m = None if oracle is None else metrics[oracle]

    def one(name: str) -> dict:
        m = metrics[name]
        b, p = base.median_rms_nm, m.median_rms_nm
        entry = {"median_rms_nm": p,
                 "variance_ratio": _variance_ratio(b, p),
                 "variance_ratio_spread": _paired(base.realisation_median_rms_nm, m.realisation_median_rms_nm,
                                                  _variance_ratio),
                 "rms_ratio": b / p if p else None,
                 "rms_ratio_spread": _paired(base.realisation_median_rms_nm, m.realisation_median_rms_nm,
                                             lambda x, y: x / y if y else None),
                 "after_fitting_variance_ratio": None if fitting is None else _after_fitting(b, p, fitting),
                 "after_fitting_variance_ratio_spread": None if fitting is None else _paired(
                     base.realisation_median_rms_nm, m.realisation_median_rms_nm,
                     lambda x, y: _after_fitting(x, y, fitting)),
                 "raw_contrast": _contrast_ratios(metrics, m, classical)}
        if oracle_m is not None:
            o = oracle_m.median_rms_nm
            entry["eta"] = eta(b, p, o)
            entry["eta_spread"] = _paired(
                list(zip(base.realisation_median_rms_nm, oracle_m.realisation_median_rms_nm, strict=False)),
                m.realisation_median_rms_nm, lambda bo, y: eta(bo[0], y, bo[1]))
        return entry

    out = {"over": best_classical, "variance_over": over,
           "variance": "median RMS squared (per-frame spatial RMS, median over the scored frames)",
           "fitting_nm": fitting,
           "after_fitting_how": FITTING_ESTIMATE if fitting is not None else NO_FITTING[over],
           "predictors": {name: one(name) for name in predictors}, "oracle": None}
    if oracle_m is not None:
        oracle_entry = one(oracle)
        oracle_entry.pop("eta", None)
        oracle_entry.pop("eta_spread", None)
        out["oracle"] = {"name": oracle, "knowledge": ORACLE_KNOWLEDGE, **oracle_entry}
    return out


#: Why a verdict has no after-fitting ratio, by where the residual is scored.
NO_FITTING = {"actuators": "no fitting error: the zonal sensor scores the residual at the actuators, where there is none",
              "pupil": "no fitting error estimate: the residual is scored over the pupil, but no error budget was "
                       "asked (evaluation.error_budget: false), so no after-fitting ratio"}


#: What an oracle knows that a real user would not (said wherever its numbers are).
ORACLE_KNOWLEDGE = ("learns from the simulator's true turbulence (its target is the true future turbulence the loop "
                    "must cancel) with ample data and more reach than any contender: knowledge no telescope has; a "
                    "bound on linear prediction from these inputs, not a contender")


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
        "dm_gain", "ratios"}}}`` (``ratios``: :func:`predictor_ratios`, every predictor's and the oracle's); a
        contender is ``None`` when none of its kind held (a diverged or diverging run is never best: it is listed in
        ``diverged`` or ``diverging`` instead; an oracle is never a contender).
    """
    scenarios = list(result.metrics)
    out = {"realisations": realisations, "scenarios": {}}
    for scenario, preds in result.metrics.items():
        held = {role: [] for role in ("predictor", "oracle", "classical", "reference")}
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
        oracle = _best(held["oracle"])
        ratios = predictor_ratios(preds, [e["name"] for e in held["predictor"]], [e["name"] for e in held["classical"]],
                                  None if best_classical is None else best_classical["name"],
                                  None if oracle is None else oracle["name"])
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
            "ratios": ratios,
        }
    return out


__all__ = ["FITTING_ESTIMATE", "ORACLE_KNOWLEDGE", "RATIO_SEPARATIONS", "build_verdict", "contender_roles", "eta",
           "predictor_ratios"]
