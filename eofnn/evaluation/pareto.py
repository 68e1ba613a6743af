"""Performance beside robustness: each controller family along its tuning path, median RMS against the width of
its stable DM-gain interval.

A predictor whose ridge alpha was chosen on validation data (``alpha: auto``) is redrawn at alphas along its path
(the same fit, other alphas: :meth:`~eofnn.training.alpha.RidgePath.weights`); a best-gain integrator at every gain
its scan tried; any other linear controller is one point. Every point closes the loop on a stream of its own
(``"pareto"``: never the test stream, so a user may choose from it), in the experiment's first scenario (or the
one named), and its analytic stable DM-gain interval is relative to that scenario's DM gain. Nonlinear
controllers have no analytic interval and are left out.
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass, field, replace

from eofnn.analysis.linear import controller_stability
from eofnn.analysis.stability import LoopSetup, StabilityResult, analyse_filter
from eofnn.control.predictive import PredictiveController
from eofnn.control.registry import build_controller, dm_gain_model_of
from eofnn.evaluation.experiment import Experiment
from eofnn.models.linear import LinearFilter
from eofnn.sim.loop.runner import Controller

#: Most points drawn along one ridge path (evenly spaced over it, the chosen alpha always among them).
MAX_PATH_POINTS = 9


@dataclass
class ParetoResult:
    """Points per family: ``{"setting", "value", "median_rms_nm" (None: diverged), "dm_gain_interval", "width",
    "chosen"}``."""

    scenario: str
    families: dict[str, list[dict]] = field(default_factory=dict)
    #: The DM-gain interval a predictor's ``optimization.select`` asked for (the first asked), relative to the
    #: scenario's DM gain; each point then says whether its interval contains it (``meets``). ``None``: none asked.
    required: tuple[float, float] | None = None

    def to_json(self) -> str:
        required = {} if self.required is None else {"required_dm_gain_interval": list(self.required)}
        return json.dumps({"scenario": self.scenario, "stream": "pareto", **required, "families": self.families},
                          indent=1)

    def markdown(self) -> str:
        lines = [f"# Performance beside robustness ({self.scenario})", "",
                 "Median RMS on a stream of its own (not the test stream) against the analytic stable DM-gain "
                 "interval, relative to the scenario's DM gain; `*` marks each family's chosen setting"
                 + ("." if self.required is None else
                    "; the last column says whether the interval contains [{:g}, {:g}].".format(*self.required)), "",
                 "| controller | setting | median RMS (nm) | stable DM gain | width |"
                 + ("" if self.required is None else " contains it |"),
                 "|---|---|---|---|---|" + ("" if self.required is None else "---|")]
        for name, points in self.families.items():
            for p in points:
                rms = "diverged" if p["median_rms_nm"] is None else f"{p['median_rms_nm']:.3g}"
                interval = ("unstable" if p["dm_gain_interval"] is None
                            else "{:.3g} to {:.3g}".format(*p["dm_gain_interval"]))
                width = "—" if p["width"] is None else f"{p['width']:.3g}"
                setting = p["setting"] if p["value"] is None else f"{p['setting']} {p['value']:g}"
                meets = "" if self.required is None else (" yes |" if p.get("meets") else " no |")
                lines.append(f"| {name}{' *' if p['chosen'] else ''} | {setting} | {rms} | "
                             f"{interval} | {width} |{meets}")
        return "\n".join(lines) + "\n"


def _interval(result: StabilityResult | None, plant_dm_gain: float) -> tuple[list[float] | None, float | None]:
    if result is None or not result.stable:
        return None, None
    low, high = result.gain_margin
    low, high = max(low, 0.0) / plant_dm_gain + 0.0, high / plant_dm_gain
    return [low, high], (high - low) if math.isfinite(high) else None


def _path_alphas(alphas: tuple[float, ...], val_loss: list[float], chosen: float) -> list[float]:
    finite = [a for a, v in zip(alphas, val_loss, strict=True) if math.isfinite(v)]
    step = max(1, math.ceil(len(finite) / MAX_PATH_POINTS))
    return sorted(set(finite[::step]) | {chosen})


def pareto(experiment: Experiment, scenario_name: str | None = None) -> ParetoResult:
    """The performance-robustness points of every linear controller family of ``experiment`` in ``scenario_name``
    (the first scenario by default)."""
    scenario_name = scenario_name or next(iter(experiment.scenarios))
    scenario = experiment.scenarios[scenario_name]
    ev = experiment.evaluation
    plant_gain = scenario.plant.dm_gain

    def median_rms(controller: Controller) -> float | None:
        return scenario.median_residual_nm(controller, ev.frames, ev.seed, "pareto", ev.settle_frames,
                                           realisations=ev.realisations, divergence_factor=ev.divergence_factor)

    asked = [cfg.optimization.dm_gain_interval for cfg in experiment.predictors.values() if cfg.trains]
    out = ParetoResult(scenario_name, required=next((tuple(a) for a in asked if a is not None), None))
    for name, cfg in experiment.predictors.items():
        run_cfg = experiment.config(name, scenario_name)
        predictor = experiment.predictor_if_any(name, scenario_name)
        path = getattr(predictor, "ridge_path", None)
        points = []
        if path is not None and isinstance(predictor.network, LinearFilter):
            chosen = predictor.info["alpha_choice"]["alpha"]
            gain_model = dm_gain_model_of(run_cfg, predictor)
            setup = LoopSetup.from_plant(scenario.plant, scenario.frame_rate_hz, gain_model)
            for alpha in _path_alphas(path.alphas, path.val_loss, chosen):
                network = copy.deepcopy(predictor.network)
                network.load_solution(path.weights(alpha).to(network.weight.dtype))
                interval, width = _interval(analyse_filter(network, predictor.spec, setup), plant_gain)
                rms = median_rms(PredictiveController(network, predictor.spec, gain_model))
                points.append({"setting": "alpha", "value": alpha, "median_rms_nm": rms, "dm_gain_interval": interval,
                               "width": width, "chosen": alpha == chosen})
        elif cfg.gains is not None:
            for gain_text in experiment.gain_scans[(name, scenario_name)]["scanned"]:
                gain_cfg = replace(run_cfg, gain=float(gain_text))
                interval, width = _interval(controller_stability(gain_cfg, None, scenario), plant_gain)
                points.append({"setting": "gain", "value": float(gain_text),
                               "median_rms_nm": median_rms(build_controller(gain_cfg)),
                               "dm_gain_interval": interval, "width": width, "chosen": float(gain_text) == run_cfg.gain})
        else:
            result = controller_stability(run_cfg, predictor, scenario)
            if result is None:
                continue  # no linear model: no analytic interval
            interval, width = _interval(result, plant_gain)
            points.append({"setting": "as configured", "value": None,
                           "median_rms_nm": median_rms(experiment.controller(name, scenario_name)),
                           "dm_gain_interval": interval, "width": width, "chosen": True})
        if points and out.required is not None:
            low, high = out.required
            for p in points:
                p["meets"] = (p["median_rms_nm"] is not None and p["dm_gain_interval"] is not None
                              and p["dm_gain_interval"][0] <= low and p["dm_gain_interval"][1] >= high)
        if points:
            out.families[name] = points
    return out
