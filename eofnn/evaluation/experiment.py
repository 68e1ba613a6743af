"""An experiment: scenarios (plants) x controllers, predictors trained once where asked, evaluated in closed loop."""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable, Collection
from dataclasses import replace
from pathlib import Path
from typing import Any

from eofnn.analysis.block import CoupledAnalysisUnavailable
from eofnn.analysis.linear import controller_stability
from eofnn.analysis.linear import summary as stability_summary
from eofnn.control.registry import FROM_TELEMETRY, NEEDS_PREDICTOR, build_controller
from eofnn.errors import require
from eofnn.evaluation.budget import budget_line, budget_runs, fitting_nm
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig, with_setting
from eofnn.evaluation.contenders import (
    SCAN_FIELDS,
    build_scenarios,
    check_experiment,
    fit_from_config,
    oracle_config,
    scan_classical_settings,
    scan_integrator_gains,
)
from eofnn.evaluation.contrast import scenario_contrast
from eofnn.evaluation.fallback import FallbackDecision, decide_fallback, fallback_scan_config
from eofnn.evaluation.metrics import GrowthMonitor, LoopMetrics, WelchPSD, loop_metrics
from eofnn.evaluation.nonstationary import reconvergence
from eofnn.evaluation.results import ExperimentResult, by_scenario, describe_run, describe_setting_scan
from eofnn.evaluation.sharing import LoopSharing, loop_key
from eofnn.evaluation.verdict import build_verdict, contender_roles
from eofnn.resources import peak_resident_bytes
from eofnn.sim.loop.runner import Controller, run_loop
from eofnn.sim.scenario import Scenario
from eofnn.training.fit import FitOutput, TrainedPredictor


def predictor_configs(scenarios: dict[str, dict[str, Any]], predictors: dict[str, PredictorConfig | dict],
                      evaluation: EvaluationConfig) -> dict[str, PredictorConfig]:
    """The controllers' configs (mappings made :class:`PredictorConfig`), once what the experiment's names can
    refuse is refused, each in one line: no controller, no scenario, or an ``oracle`` name that
    ``evaluation.oracle`` would add a second time."""
    configs = ({name: cfg if isinstance(cfg, PredictorConfig) else PredictorConfig(**cfg)
                for name, cfg in predictors.items()} if isinstance(predictors, dict) else predictors)
    require(isinstance(configs, dict) and len(configs) >= 1, "predictors is empty: give at least one")
    require(isinstance(scenarios, dict) and len(scenarios) >= 1, "scenarios is empty: give at least one, e.g. "
            "nominal: {}")
    require(not evaluation.oracle or "oracle" not in configs or any(cfg.oracle for cfg in configs.values()),
            "evaluation.oracle: true adds a controller named 'oracle', and predictors already has one: rename it, or "
            "mark it oracle: true")
    return configs


class Experiment:
    """Validates everything up front, then trains, evaluates and collects metrics.

    Parameters
    ----------
    scenario : Scenario
        Telescope, atmosphere, frame rate and base plant shared by all scenarios.
    scenarios : dict
        Scenario name -> plant changes (model errors).
    predictors : dict
        Controller name -> :class:`PredictorConfig`.
    evaluation : EvaluationConfig
        Closed-loop evaluation settings.
    checkpoint_dir : path, optional
        Where trained predictors are saved.
    progress : bool or None
        Progress bars (``None``: only on a terminal).
    log : callable
        Where progress lines go.
    trusted_networks : collection of str
        Network class paths, beyond eofnn's own, that checkpoints may name.
    share_loops : bool
        Close a loop once where contenders run the same one (:mod:`eofnn.evaluation.sharing`; the same numbers).
    """

    def __init__(self, scenario: Scenario, scenarios: dict[str, dict[str, Any]],
                 predictors: dict[str, PredictorConfig], evaluation: EvaluationConfig,
                 checkpoint_dir: str | Path | None = None, progress: bool | None = None,
                 log: Callable[[str], None] = print, trusted_networks: Collection[str] = (),
                 allow_long: bool = False, share_loops: bool = True) -> None:
        self.predictors = predictor_configs(scenarios, predictors, evaluation)
        self.scenarios = build_scenarios(scenario, scenarios)
        if evaluation.oracle and not any(cfg.oracle for cfg in self.predictors.values()):
            self.predictors["oracle"] = oracle_config(self.predictors, next(iter(self.scenarios.values())))
        self.evaluation = evaluation
        self.checkpoint_dir = Path(checkpoint_dir) if checkpoint_dir is not None else None
        self.progress, self.log = progress, log
        self._trained: dict[tuple[str, str], TrainedPredictor] = {}
        #: The nominal filter's stability in each later scenario (:meth:`nominal_filter_stability`), once computed.
        self._nominal_stability: dict[tuple[str, str], dict | None] = {}
        #: Best-gain integrators: (controller, scenario) -> {"gain": chosen, "scanned": {gain: median RMS or None}}.
        self.gain_scans: dict[tuple[str, str], dict] = {}
        #: Classical controllers whose settings were tuned on a stream of their own (the extrapolator's order and
        #: smoothing, the LQG's AR order): (controller, scenario) -> {**chosen setting, "median_rms_nm", "scanned"}.
        self.setting_scans: dict[tuple[str, str], dict] = {}
        #: Ridge alphas chosen on validation data (``alpha: auto``): (controller, training scenario) -> choice.
        self.alpha_choices: dict[tuple[str, str], dict] = {}
        #: Budgeted searches of networks trained by SGD: (controller, training scenario) -> trials, choice, budget.
        self.searches: dict[tuple[str, str], dict] = {}
        #: Classical models built from telemetry (modal integrator, LQG): (controller, scenario) -> model.
        self.classical_models: dict[tuple[str, str], Any] = {}
        self.checkpoints: dict[str, str] = {}
        #: Fallbacks to the best-gain integrator (``fallback:``): (controller, scenario) -> decision.
        self.fallbacks: dict[tuple[str, str], FallbackDecision] = {}
        #: Gain scans, scored loops and fitting errors that contenders share (:mod:`eofnn.evaluation.sharing`).
        self.sharing = LoopSharing(share_loops)
        self._loaded = check_experiment(self.scenarios, self.predictors, evaluation, trusted_networks, allow_long)
        if evaluation.psd_segment_note is not None:
            self.log(evaluation.psd_segment_note)

    def predictor(self, name: str, scenario_name: str) -> TrainedPredictor:
        """The trained predictor ``name`` for evaluation in ``scenario_name`` (trained on first use)."""
        if name in self._loaded:
            return self._loaded[name]
        cfg = self.predictors[name]
        train_in = cfg.train_in or scenario_name
        key = (name, train_in)
        if key not in self._trained:
            path = None if self.checkpoint_dir is None else self.checkpoint_dir / f"{name}__{train_in}.ckpt"
            same = next((other for other, where in self._trained if where == train_in and other not in self._loaded
                         and _training(self.predictors[other]) == _training(cfg)), None)
            if same is not None:  # the same training (a guarded copy of a contender): its result, not a refit
                self.log(f"{train_in:>12s} {name:>18s}: trained as {same} is (the same config but its fallback)")
                result = self._trained[(same, train_in)]
                if path is not None and (self.checkpoint_dir / f"{same}__{train_in}.ckpt").exists():
                    shutil.copyfile(self.checkpoint_dir / f"{same}__{train_in}.ckpt", path)
            else:
                self.log(f"training {name} in scenario {train_in} ({cfg.history}, p={cfg.history_length}, "
                         f"{cfg.optimization.fit_method}, {cfg.data.learns_from})")
                result = fit_from_config(self.scenarios[train_in], cfg,
                                         FitOutput(path, True, bool(self.progress))).predictor
            self._trained[key] = result
            searched = result.info.get("search")
            if searched is not None:
                self.searches[key] = searched
                chosen, budget = searched["chosen"], searched["budget"]
                self.log(f"{train_in:>12s} {name:>18s}: lr {chosen['lr']:g}"
                         + ("" if chosen["width"] is None else f", width {chosen['width']}")
                         + f" chosen on validation data (best epoch {chosen['best_epoch']}); budget {budget['trials']} "
                         f"trials, {budget['epochs']} epochs, {budget['frames']} frames")
            choice = result.info.get("alpha_choice")
            if choice is not None:
                self.alpha_choices[key] = choice
                where = "" if "dm_gain_interval" not in choice else (
                    " (stable DM gain {:.3g} to {:.3g})".format(*choice["dm_gain_interval"]))
                self.log(f"{train_in:>12s} {name:>18s}: ridge alpha {choice['alpha']:g} chosen on validation data "
                         f"of {len(choice['path']['alpha'])} on the path{where}")
            if path is not None:
                self.checkpoints[f"{name}/{train_in}"] = f"{path.parent.name}/{path.name}"
        return self._trained[key]

    def predictor_if_any(self, name: str, scenario_name: str) -> TrainedPredictor | None:
        """The trained predictor of controller ``name`` if it runs one (baselines run none), or the model a classical
        controller builds from telemetry recorded in the scenario (on a stream of its own, like the gain scan)."""
        if self.predictors[name].controller in FROM_TELEMETRY:
            key = (name, scenario_name)
            if self.predictors[name].setting_grid is not None:
                self._tuned(name, scenario_name)  # builds (and keeps) the chosen setting's model
            if key not in self.classical_models:
                cfg = self.predictors[name]
                self.classical_models[key] = FROM_TELEMETRY[cfg.controller](cfg, self.scenarios[scenario_name])
                self.log(f"{scenario_name:>12s} {name:>18s}: built from {cfg.data.frames} frames of telemetry")
            return self.classical_models[key]
        return self.predictor(name, scenario_name) if self.predictors[name].controller in NEEDS_PREDICTOR else None

    def config(self, name: str, scenario_name: str) -> PredictorConfig:
        """Controller ``name``'s config as it runs in ``scenario_name``: a best-gain integrator has its gain chosen, a
        tuned extrapolator its order and smoothing, a tuned LQG its AR order and noise scale."""
        cfg = self.predictors[name]
        if cfg.setting_grid is not None:
            chosen = {key: value for key, value in self._tuned(name, scenario_name).items()
                      if key not in ("median_rms_nm", "scanned")}
            return with_setting(replace(cfg, **dict.fromkeys(SCAN_FIELDS)), chosen)
        if cfg.gains is None:
            return cfg
        key = (name, scenario_name)
        if key not in self.gain_scans:
            self.gain_scans[key] = self._integrator_scan(cfg, scenario_name)
            scan = self.gain_scans[key]
            edge = (f" — at the edge of the gains tried (critical gain {scan['critical_gain']:.3g}): extend gains"
                    if scan["at_edge"] else "")
            if not scan["at_edge"] and scan["gain"] >= 0.98 * scan["critical_gain"]:
                edge = f" — within 2% of the critical gain {scan['critical_gain']:.3g}: little stability margin"
            self.log(f"{scenario_name:>12s} {name:>18s}: best integrator gain {scan['gain']:g} of "
                     f"{', '.join(f'{g:g}' for g in cfg.gains)}, refined with {', '.join(f'{g:g}' for g in scan['refined'])}"
                     f"{edge}")
        return replace(cfg, gains=None, gain=self.gain_scans[key]["gain"])

    def _integrator_scan(self, cfg: PredictorConfig, scenario_name: str) -> dict:
        """The best-gain integrator scan of ``cfg`` in ``scenario_name`` (a guard's too), shared by every scan alike."""
        ev = self.evaluation
        return self.sharing.scan(cfg, scenario_name, ev.settle_frames, ev.divergence_factor, lambda: scan_integrator_gains(
            cfg, self.scenarios[scenario_name], ev.settle_frames, ev.divergence_factor))

    def _tuned(self, name: str, scenario_name: str) -> dict:
        """The scan of classical controller ``name``'s settings in ``scenario_name`` (run on first use, on a stream of
        its own: :func:`~eofnn.evaluation.contenders.scan_classical_settings`); the chosen setting's model, if it has
        one, is kept as the model it runs with."""
        cfg, key = self.predictors[name], (name, scenario_name)
        if key not in self.setting_scans:
            scan, model = scan_classical_settings(cfg, self.scenarios[scenario_name], self.evaluation.settle_frames,
                                                  self.evaluation.divergence_factor)
            self.setting_scans[key] = scan
            if model is not None:
                self.classical_models[key] = model
            built = f" (each built from {cfg.data.frames} frames of telemetry)" if model is not None else ""
            self.log(f"{scenario_name:>12s} {name:>18s}: {describe_setting_scan(scan)} on a stream of its own{built}")
        return self.setting_scans[key]

    def controller(self, name: str, scenario_name: str) -> Controller:
        """The controller ``name`` as it runs in ``scenario_name`` (with a ``fallback:``, what its decision deploys)."""
        predictor = self.predictor_if_any(name, scenario_name)
        config = self.config(name, scenario_name)
        if not config.fallback.active:
            return build_controller(config, predictor)
        return self.fallback(name, scenario_name).build(lambda: build_controller(config, predictor))

    def fallback(self, name: str, scenario_name: str) -> FallbackDecision:
        """Where controller ``name`` falls back to the best-gain integrator in ``scenario_name`` (decided on first use,
        on a stream of its own: :func:`~eofnn.evaluation.fallback.decide_fallback`)."""
        key = (name, scenario_name)
        if key not in self.fallbacks:
            predictor = self.predictor_if_any(name, scenario_name)
            config = self.config(name, scenario_name)
            decision = decide_fallback(lambda: build_controller(config, predictor), config.fallback,
                                       self.scenarios[scenario_name], self.evaluation.divergence_factor,
                                       self.evaluation.settle_frames,
                                       self._integrator_scan(fallback_scan_config(config.fallback), scenario_name))
            self.fallbacks[key] = decision
            report = decision.report
            modes = "" if "n_modes" not in report else (
                f"; predictor on {report['predictor_modes']} of {report['n_modes']} "
                f"{'KL modes' if report['modes'] == 'kl' else 'actuators'}")
            self.log(f"{scenario_name:>12s} {name:>18s}: fallback per {report['per']}: {decision.deployed} deployed "
                     f"(integrator gain {decision.gain:g}{modes}): {report['why']}")
        return self.fallbacks[key]

    def evaluate(self, name: str, scenario_name: str, plant_scenario: Scenario | None = None) -> LoopMetrics:
        """Closed-loop metrics of controller ``name`` as made for ``scenario_name``, on the test stream (those of a
        contender that ran the same loops, :mod:`eofnn.evaluation.sharing`).

        ``plant_scenario`` runs that same controller in another plant (a robustness map); by default it runs in
        the scenario it was made for.
        """
        if plant_scenario is not None:
            return self._evaluate(name, scenario_name, plant_scenario)
        predictor = self.predictor_if_any(name, scenario_name)  # in the order controller() makes them
        config = self.config(name, scenario_name)
        deployed = self.fallback(name, scenario_name).deployed if config.fallback.active else None

        def note(other: str, metrics: LoopMetrics) -> None:
            self.log(f"{scenario_name:>12s} {name:>18s}: the loops {other} closed (the same controller, plant and "
                     "streams): not closed again")
            if metrics.error_budget is not None:
                self.log(f"{scenario_name:>12s} {name:>18s}: {budget_line(metrics.error_budget)}")

        return self.sharing.scored(loop_key(config, predictor, scenario_name, deployed), predictor, name,
                                   lambda: self._evaluate(name, scenario_name), note)

    def _evaluate(self, name: str, scenario_name: str, plant_scenario: Scenario | None = None) -> LoopMetrics:
        ev = self.evaluation
        scenario = plant_scenario if plant_scenario is not None else self.scenarios[scenario_name]
        controller = self.controller(name, scenario_name)
        psd = WelchPSD(ev.psd_segment_frames_used, scenario.frame_rate_hz, ev.settle_frames)
        contrast = scenario_contrast(scenario, ev.strehl_wavelength_m, ev.settle_frames)
        growth = GrowthMonitor(scenario.frame_rate_hz, ev.settle_frames)
        turbulence, probe = scenario.turbulence(ev.seed, "test", ev.realisations), None
        if plant_scenario is None and scenario.sensor.is_pyramid and self.predictors[name].controller == "integrator":
            from eofnn.sim.sensing.optical_gains import OpticalGainProbe  # its optical gains on the residual

            probe = OpticalGainProbe.of(turbulence, ev.settle_frames, ev.frames, scenario.plant)

        def on_chunk(first: int, arrays: dict) -> None:
            psd(first, arrays)
            contrast(first, arrays)
            growth(first, arrays)
            if probe is not None:  # a pyramid's optical gains on the (best-gain) integrator's residual
                probe(first, arrays)

        result = run_loop(turbulence, scenario.plant, controller,
                          ev.frames, noise_seed=ev.seed, record=(), divergence_factor=ev.divergence_factor,
                          progress=self.progress, on_chunk=on_chunk)
        optical = None if probe is None or result.diverged else probe.result()
        metrics = loop_metrics(result, ev.settle_frames, ev.strehl_wavelength_m, psd)
        metrics.fallback_frame = getattr(controller, "fallback_frame", None)
        if not result.diverged:
            metrics.growth = growth.result()
            metrics.diverging = bool(metrics.growth and metrics.growth["diverging"])
        metrics.optical_gains = optical
        if not result.diverged:
            metrics.contrast_separation_lod, metrics.contrast = contrast.profile()
            metrics.contrast_at = contrast.at()
            metrics.realisation_contrast_at = contrast.realisations_at()
            metrics.spatial_split_nm = contrast.spatial_split()
        wanted = ev.error_budget if ev.error_budget is not None else scenario.sensor.is_shack_hartmann
        if plant_scenario is None and wanted and not result.diverged:  # a diverged run has no budget to split
            fitting = self.sharing.fitting((scenario_name, ev.seed, "test", ev.frames, ev.settle_frames,
                                            ev.realisations), lambda: fitting_nm(scenario, ev.seed, "test", ev.frames,
                                                                                 ev.settle_frames, ev.realisations))
            metrics.error_budget = budget_runs(scenario, lambda: self.controller(name, scenario_name), ev,
                                               metrics.median_rms_nm, fitting)
            self.log(f"{scenario_name:>12s} {name:>18s}: {budget_line(metrics.error_budget)}")
        return metrics

    def stability(self, name: str, scenario_name: str) -> dict | None:
        """Analytic stability summary of controller ``name`` in ``scenario_name`` (``None`` if not linear)."""
        if not self.evaluation.analytic_stability:
            return None
        predictor = self.predictor_if_any(name, scenario_name)
        config, scenario = self.config(name, scenario_name), self.scenarios[scenario_name]
        try:
            result = controller_stability(config, predictor, scenario,
                                          self.fallback(name, scenario_name) if config.fallback.active else None)
        except CoupledAnalysisUnavailable as err:  # reported like a network's: no analytic margins
            self.log(f"{scenario_name:>12s} {name:>18s}: no analytic stability: {err}")
            return None
        return None if result is None else stability_summary(result, scenario)

    def nominal_filter_stability(self, name: str, scenario_name: str) -> dict | None:
        """The analytic stability, in ``scenario_name``'s plant, of predictor ``name`` as trained in the first
        (nominal) scenario: would the nominal filter hold where it was retrained? ``None`` when that filter was not
        trained, has no linear model, or is too large to analyse. Kept once computed: compare builds the verdict again
        when simulated margins come in, and a coupled filter's analysis takes a while."""
        key = (name, scenario_name)
        if key not in self._nominal_stability:
            self._nominal_stability[key] = self._analyse_nominal_filter(name, scenario_name)
        return self._nominal_stability[key]

    def _analyse_nominal_filter(self, name: str, scenario_name: str) -> dict | None:
        trained = self._trained.get((name, next(iter(self.scenarios))))
        if trained is None or not self.evaluation.analytic_stability:
            return None
        try:
            result = controller_stability(self.config(name, scenario_name), trained, self.scenarios[scenario_name])
        except CoupledAnalysisUnavailable:
            return None
        return None if result is None else stability_summary(result, self.scenarios[scenario_name])

    def verdict(self, result: ExperimentResult) -> dict:
        """The verdict of ``result`` per scenario (:func:`eofnn.evaluation.verdict.build_verdict`)."""
        return build_verdict(result, contender_roles(self.predictors), self.evaluation.realisations,
                             self.nominal_filter_stability)

    def run(self) -> ExperimentResult:
        metrics: dict[str, dict[str, LoopMetrics]] = {}
        stability: dict[str, dict[str, dict]] = {}
        timings, peaks = {}, {}
        gains_used: dict[tuple[str, str], dict] = {}
        for scenario_name in self.scenarios:
            metrics[scenario_name], stability[scenario_name] = {}, {}
            for name in self.predictors:
                start = time.perf_counter()
                m = self.evaluate(name, scenario_name)
                timings[f"{scenario_name}/{name}"] = round(time.perf_counter() - start, 3)
                peaks[f"{scenario_name}/{name}"] = peak_resident_bytes()
                metrics[scenario_name][name] = m
                margins = self.stability(name, scenario_name)
                if margins is not None:
                    stability[scenario_name][name] = margins
                gain_note = ""
                if self.predictors[name].controller == "integrator":
                    scanned = self.predictors[name].gains is not None
                    gain = self.config(name, scenario_name).gain
                    gains_used[(name, scenario_name)] = {"gain": gain, "scanned": scanned}
                    gain_note = f"; gain {gain:g} ({'best of the scan' if scanned else 'fixed, not tuned'})"
                self.log(f"{scenario_name:>12s} {name:>18s}: {describe_run(m, margins, self.scenarios[scenario_name])}"
                         f"{gain_note}")
            changes = self.scenarios[scenario_name].changes()
            if changes:
                runs = {name: None if m.diverged else m.rms_nm for name, m in metrics[scenario_name].items()}
                rate = self.scenarios[scenario_name].frame_rate_hz
                for name, entries in reconvergence(runs, changes, rate).items():
                    metrics[scenario_name][name].reconvergence = entries
        models = {key: model.info for key, model in self.classical_models.items()}
        result = ExperimentResult(metrics, dict(self.checkpoints), timings, stability, by_scenario(self.gain_scans),
                                  by_scenario(self.alpha_choices), by_scenario(self.searches),
                                  classical_models=by_scenario(models), peak_memory_bytes=peaks,
                                  scenario_dm_gains={name: float(sc.plant.dm_gain)
                                                     for name, sc in self.scenarios.items()},
                                  integrator_gain_used=by_scenario(gains_used),
                                  classical_settings=by_scenario(self.setting_scans),
                                  fallbacks=by_scenario({key: decision.report
                                                          for key, decision in self.fallbacks.items()}))
        result.verdict = self.verdict(result)
        return result


def _training(cfg: PredictorConfig) -> str:  # what trains cfg's predictor: its config but the fallback
    return repr(replace(cfg, fallback=type(cfg.fallback)()))
