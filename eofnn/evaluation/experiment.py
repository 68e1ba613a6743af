"""An experiment: scenarios (plants) x controllers, predictors trained once where asked, evaluated in closed loop."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Collection
from dataclasses import replace
from pathlib import Path
from typing import Any

from eofnn.analysis.block import CoupledAnalysisTooLarge
from eofnn.analysis.linear import controller_stability, dm_gain_margin
from eofnn.analysis.linear import summary as stability_summary
from eofnn.analysis.stability import LoopSetup, analyse_integrator
from eofnn.control.baselines import Integrator
from eofnn.control.modal import require_telemetry
from eofnn.control.registry import FROM_TELEMETRY, NEEDS_PREDICTOR, build_controller
from eofnn.data.history import HistorySpec
from eofnn.data.stream import require_training_memory
from eofnn.errors import CheckpointError, ConfigError, require
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
from eofnn.evaluation.contrast import RawContrast
from eofnn.evaluation.metrics import GrowthMonitor, LoopMetrics, WelchPSD, loop_metrics
from eofnn.evaluation.nonstationary import reconvergence, require_changes_within, scenario_changes
from eofnn.evaluation.results import ExperimentResult
from eofnn.resources import peak_resident_bytes, require_memory, require_time
from eofnn.sim.loop import Controller, run_loop
from eofnn.sim.scenario import Scenario
from eofnn.training.checkpoint import load_predictor
from eofnn.training.fit import FitOutput, FitResult, TrainedPredictor, fit_predictor
from eofnn.training.from_telemetry import fit_from_scenario_telemetry, telemetry_sequences


def fit_from_config(scenario: Scenario, cfg: PredictorConfig, output: FitOutput | None = None) -> FitResult:
    """Train the predictor ``cfg`` describes on telemetry simulated in ``scenario``: against the simulator's truth,
    or (``data.truth: false``) from the telemetry alone, through the plant identified from its dither."""
    margin = dm_gain_margin(scenario.frame_rate_hz) if cfg.optimization.select is not None else None
    fit = fit_predictor if cfg.data.truth else fit_from_scenario_telemetry
    return fit(scenario, cfg.history, cfg.history_length, cfg.network, data=cfg.data, optimization=cfg.optimization,
               output=output, margin=margin)


def build_scenarios(base: Scenario, scenarios: dict[str, dict[str, Any]]) -> dict[str, Scenario]:
    """The base scenario with each entry's plant changes (``{}`` is the base plant)."""
    require(isinstance(scenarios, dict) and len(scenarios) >= 1,
            "scenarios is empty: give at least one, e.g. nominal: {}")
    out = {}
    for name, changes in scenarios.items():
        if changes is not None and not isinstance(changes, dict):
            raise ConfigError(f"scenario {name!r}: {changes!r} is invalid: give a mapping of plant fields, e.g. "
                              "{dm_gain: 2.0}")
        try:
            out[name] = base.with_plant(**(changes or {}))
        except (ConfigError, TypeError) as err:
            raise ConfigError(f"scenario {name!r}: {err}") from None
    return out


def trusted_class_paths(predictors: dict[str, PredictorConfig], extra: Collection[str] = ()) -> set[str]:
    """Network class paths the user named (in the config or on the command line): checkpoints may name these."""
    named = {cfg.network["class_path"] for cfg in predictors.values() if cfg.network is not None}
    return named | set(extra)


def load_configured_checkpoint(name: str, cfg: PredictorConfig, scenarios: dict[str, Scenario],
                               trusted: Collection[str]) -> TrainedPredictor:
    """The checkpoint of controller ``name``, checked against its config (history) and every scenario it runs in."""
    predictor = load_predictor(cfg.checkpoint, trusted_networks=trusted)
    where = f"predictor {name!r}: checkpoint {cfg.checkpoint!r}"
    if cfg.history is not None and cfg.history != predictor.spec.kind:
        raise CheckpointError(f"{where} holds a {predictor.spec.kind} predictor but history={cfg.history!r} was "
                              "asked for")
    for scenario_name, scenario in scenarios.items():
        predictor.check_fits(scenario, f"{where} in scenario {scenario_name!r}", cfg.history_length)
    return predictor


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
    """

    def __init__(self, scenario: Scenario, scenarios: dict[str, dict[str, Any]],
                 predictors: dict[str, PredictorConfig], evaluation: EvaluationConfig,
                 checkpoint_dir: str | Path | None = None, progress: bool | None = None,
                 log: Callable[[str], None] = print, trusted_networks: Collection[str] = (),
                 allow_long: bool = False) -> None:
        require(isinstance(predictors, dict) and len(predictors) >= 1, "predictors is empty: give at least one")
        self.scenarios = build_scenarios(scenario, scenarios)
        self.predictors = {name: cfg if isinstance(cfg, PredictorConfig) else PredictorConfig(**cfg)
                           for name, cfg in predictors.items()}
        self.evaluation = evaluation
        n_act = max(s.grid.n_actuators for s in self.scenarios.values())
        # Per frame and realisation two RMS values are kept; per realisation a turbulence chunk of 1024 frames
        # and the arrays of that chunk (s, y, eps, wfs) are in flight.
        require_memory(8 * evaluation.realisations * (2 * evaluation.frames + 5 * 1024 * n_act),
                       f"evaluation with evaluation.frames={evaluation.frames}, evaluation.realisations="
                       f"{evaluation.realisations} and {n_act} actuators")
        self.checkpoint_dir = Path(checkpoint_dir) if checkpoint_dir is not None else None
        self.progress, self.log = progress, log
        self._trained: dict[tuple[str, str], TrainedPredictor] = {}
        self._loaded: dict[str, TrainedPredictor] = {}
        #: Best-gain integrators: (controller, scenario) -> {"gain": chosen, "scanned": {gain: median RMS or None}}.
        self.gain_scans: dict[tuple[str, str], dict] = {}
        #: Ridge alphas chosen on validation data (``alpha: auto``): (controller, training scenario) -> choice.
        self.alpha_choices: dict[tuple[str, str], dict] = {}
        #: Budgeted searches of networks trained by SGD: (controller, training scenario) -> trials, choice, budget.
        self.searches: dict[tuple[str, str], dict] = {}
        #: Classical models built from telemetry (modal integrator, LQG): (controller, scenario) -> model.
        self.classical_models: dict[tuple[str, str], Any] = {}
        self.checkpoints: dict[str, str] = {}
        trusted = trusted_class_paths(self.predictors, trusted_networks)
        for name, cfg in self.predictors.items():
            if cfg.trains:
                for scenario_value in self.scenarios.values():
                    spec = HistorySpec.from_scenario(cfg.history, cfg.history_length, scenario_value)
                    require_training_memory(scenario_value, spec, cfg.data)
            if cfg.train_in is not None and cfg.train_in not in self.scenarios:
                raise ConfigError(f"predictor {name!r}: train_in={cfg.train_in!r} is not a scenario: allowed are "
                                  f"{', '.join(self.scenarios)}")
            if cfg.checkpoint is not None:
                self._loaded[name] = load_configured_checkpoint(name, cfg, self.scenarios, trusted)
        # Time: every controller runs in every scenario; each trained predictor simulates its data once per scenario
        # (or once where train_in says).
        work = evaluation.frames * evaluation.realisations * n_act * len(self.predictors) * len(self.scenarios)
        work += sum(len(cfg.gains) * cfg.data.frames * n_act * len(self.scenarios)
                    for cfg in self.predictors.values() if cfg.gains is not None)
        work += sum(cfg.data.realisations * (cfg.data.frames + cfg.data.val_frames) * (cfg.data.refit_rounds + 1)
                    * n_act * (1 if cfg.train_in else len(self.scenarios))
                    for cfg in self.predictors.values() if cfg.trains)
        require_time(work, f"this experiment ({len(self.predictors)} controllers x {len(self.scenarios)} scenarios, "
                     f"{n_act} actuators)", allow_long)
        # Streams the exact turbulence screen must hold (training sequences are checked with their memory).
        for scenario_name, scenario_value in self.scenarios.items():
            scenario_value.require_stream_frames(evaluation.frames, f"evaluation.frames={evaluation.frames}",
                                                 evaluation.realisations)
            require_changes_within(scenario_value, evaluation.frames, f"scenario {scenario_name!r}")
            for name, cfg in self.predictors.items():
                if cfg.gains is not None:
                    scenario_value.require_stream_frames(cfg.data.frames, f"predictor {name!r}: data.frames="
                                                         f"{cfg.data.frames} (the gain scan)")
                elif cfg.controller in FROM_TELEMETRY:
                    require_telemetry(cfg.data, scenario_value.grid.n_actuators, cfg.modes, f"predictor {name!r}")
                    scenario_value.require_stream_frames(cfg.data.frames, f"predictor {name!r}: data.frames="
                                                         f"{cfg.data.frames} (its telemetry)")
                elif cfg.trains and not cfg.data.truth:
                    n_sequences, n, _ = telemetry_sequences(cfg.data)
                    scenario_value.require_stream_frames(n, f"predictor {name!r}: telemetry training ({n_sequences} "
                                                         f"sequence(s) of {n} frames, data.sequence_frames="
                                                         f"{cfg.data.sequence_frames})",
                                                         n_sequences * cfg.data.realisations)

    #: The most rounds of refinement of a best-gain integrator's scan (while the best is still the highest gain
    #: tried, climbing towards the critical gain).
    MAX_REFINE_ROUNDS = 6

    def predictor(self, name: str, scenario_name: str) -> TrainedPredictor:
        """The trained predictor ``name`` for evaluation in ``scenario_name`` (trained on first use)."""
        if name in self._loaded:
            return self._loaded[name]
        cfg = self.predictors[name]
        train_in = cfg.train_in or scenario_name
        key = (name, train_in)
        if key not in self._trained:
            path = None if self.checkpoint_dir is None else self.checkpoint_dir / f"{name}__{train_in}.ckpt"
            self.log(f"training {name} in scenario {train_in} ({cfg.history}, p={cfg.history_length}, "
                     f"{cfg.optimization.fit_method}, {'simulator truth' if cfg.data.truth else 'telemetry alone'})")
            result = fit_from_config(self.scenarios[train_in], cfg, FitOutput(path, True, bool(self.progress)))
            self._trained[key] = result.predictor
            searched = result.predictor.info.get("search")
            if searched is not None:
                self.searches[key] = searched
                chosen, budget = searched["chosen"], searched["budget"]
                self.log(f"{train_in:>12s} {name:>18s}: lr {chosen['lr']:g}"
                         + ("" if chosen["width"] is None else f", width {chosen['width']}")
                         + f" chosen on validation data (best epoch {chosen['best_epoch']}); budget {budget['trials']} "
                         f"trials, {budget['epochs']} epochs, {budget['frames']} frames")
            choice = result.predictor.info.get("alpha_choice")
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
            if key not in self.classical_models:
                cfg = self.predictors[name]
                self.classical_models[key] = FROM_TELEMETRY[cfg.controller](cfg, self.scenarios[scenario_name])
                self.log(f"{scenario_name:>12s} {name:>18s}: built from {cfg.data.frames} frames of telemetry")
            return self.classical_models[key]
        return self.predictor(name, scenario_name) if self.predictors[name].controller in NEEDS_PREDICTOR else None

    def config(self, name: str, scenario_name: str) -> PredictorConfig:
        """Controller ``name``'s config as it runs in ``scenario_name``: a best-gain integrator has its gain chosen."""
        cfg = self.predictors[name]
        if cfg.gains is None:
            return cfg
        key = (name, scenario_name)
        if key not in self.gain_scans:
            self.gain_scans[key] = self._scan_gains(cfg, self.scenarios[scenario_name])
            scan = self.gain_scans[key]
            edge = (f" — at the edge of the gains tried (critical gain {scan['critical_gain']:.3g}): extend gains"
                    if scan["at_edge"] else "")
            if not scan["at_edge"] and scan["gain"] >= 0.98 * scan["critical_gain"]:
                edge = f" — within 2% of the critical gain {scan['critical_gain']:.3g}: little stability margin"
            self.log(f"{scenario_name:>12s} {name:>18s}: best integrator gain {scan['gain']:g} of "
                     f"{', '.join(f'{g:g}' for g in cfg.gains)}, refined with {', '.join(f'{g:g}' for g in scan['refined'])}"
                     f"{edge}")
        return replace(cfg, gains=None, gain=self.gain_scans[key]["gain"])

    def _scan_gains(self, cfg: PredictorConfig, scenario: Scenario) -> dict:
        """Close the loop with each of ``cfg.gains`` on a stream of its own; the lowest median residual wins, after
        ``cfg.refine_rounds`` rounds of refinement between the best gain and its neighbours (past the grid's top
        up to the analytic critical gain, below its bottom down to 0), so the choice is never an edge of the grid
        unless it is the edge of what is stable (then ``at_edge`` says so)."""
        settle = min(self.evaluation.settle_frames, cfg.data.frames // 2)
        # The critical integrator gain: the loop gain at which an integrator goes unstable in a nominal plant of
        # this delay (a small gain's DM-gain margin times that gain), over this plant's DM and WFS gains.
        nominal = LoopSetup(scenario.plant.delay_frames, frame_rate_hz=scenario.frame_rate_hz)
        critical = (0.01 * float(analyse_integrator(0.01, cfg.leak, nominal).gain_margin[1])
                    / (scenario.plant.dm_gain * scenario.plant.wfs_gain))
        scanned: dict[float, float | None] = {}

        def run(gain: float) -> None:
            scanned[gain] = scenario.median_residual_nm(Integrator(gain, cfg.leak), cfg.data.frames, cfg.data.seed,
                                                        "gain-scan", settle,
                                                        divergence_factor=self.evaluation.divergence_factor)

        for gain in cfg.gains:
            run(gain)
        require(any(v is not None for v in scanned.values()),
                f"every integrator gain of gains={cfg.gains!r} diverged: give smaller gains")
        refined = []
        for round_index in range(self.MAX_REFINE_ROUNDS if cfg.refine_rounds else 0):
            gains = sorted(scanned)
            best = min((rms, g) for g, rms in scanned.items() if rms is not None)[1]
            i = gains.index(best)
            top = i + 1 == len(gains)
            if round_index >= cfg.refine_rounds and not (top and best < 0.98 * critical):
                break  # refined enough, and not still climbing towards the critical gain
            left = gains[i - 1] if i > 0 else 0.0
            right = min(gains[i + 1] if not top else critical, 0.99 * critical)
            for candidate in ((left + best) / 2, (best + right) / 2):
                candidate = float(f"{candidate:.4g}")
                if candidate > 0 and candidate not in scanned and candidate < critical:
                    run(candidate)
                    refined.append(candidate)
        finite = sorted((rms, g) for g, rms in scanned.items() if rms is not None)
        best = finite[0][1]
        gains = sorted(scanned)
        at_edge = best == gains[0] or (best == gains[-1] and best < 0.98 * critical)
        return {"gain": best, "scanned": {f"{g:g}": scanned[g] for g in gains}, "refined": refined,
                "critical_gain": critical, "at_edge": at_edge}

    def controller(self, name: str, scenario_name: str) -> Controller:
        """The controller ``name`` as it runs in ``scenario_name``."""
        predictor = self.predictor_if_any(name, scenario_name)
        return build_controller(self.config(name, scenario_name), predictor)

    def evaluate(self, name: str, scenario_name: str, plant_scenario: Scenario | None = None) -> LoopMetrics:
        """Closed-loop metrics of controller ``name`` as made for ``scenario_name``, on the test stream.

        ``plant_scenario`` runs that same controller in another plant (a robustness map); by default it runs in
        the scenario it was made for.
        """
        ev = self.evaluation
        scenario = plant_scenario if plant_scenario is not None else self.scenarios[scenario_name]
        controller = self.controller(name, scenario_name)
        psd = WelchPSD(ev.psd_segment_frames, scenario.frame_rate_hz, ev.settle_frames)
        contrast = RawContrast(scenario.grid, ev.strehl_wavelength_m, ev.settle_frames)
        growth = GrowthMonitor(scenario.frame_rate_hz, ev.settle_frames)

        def on_chunk(first: int, arrays: dict) -> None:
            psd(first, arrays)
            contrast(first, arrays)
            growth(first, arrays)

        result = run_loop(scenario.turbulence(ev.seed, "test", ev.realisations), scenario.plant, controller,
                          ev.frames, noise_seed=ev.seed, record=(), divergence_factor=ev.divergence_factor,
                          progress=self.progress, on_chunk=on_chunk)
        metrics = loop_metrics(result, ev.settle_frames, ev.strehl_wavelength_m, psd)
        metrics.fallback_frame = getattr(controller, "fallback_frame", None)
        if not result.diverged:
            metrics.growth = growth.result()
            metrics.diverging = bool(metrics.growth and metrics.growth["diverging"])
        if not result.diverged:
            metrics.contrast_separation_lod, metrics.contrast = contrast.profile()
            metrics.contrast_at = contrast.at()
        return metrics

    def stability(self, name: str, scenario_name: str) -> dict | None:
        """Analytic stability summary of controller ``name`` in ``scenario_name`` (``None`` if not linear)."""
        predictor = self.predictor_if_any(name, scenario_name)
        try:
            result = controller_stability(self.config(name, scenario_name), predictor, self.scenarios[scenario_name])
        except CoupledAnalysisTooLarge as err:  # reported like a network's: no analytic margins
            self.log(f"{scenario_name:>12s} {name:>18s}: no analytic stability: {err}")
            return None
        return None if result is None else stability_summary(result)

    def run(self) -> ExperimentResult:
        metrics: dict[str, dict[str, LoopMetrics]] = {}
        stability: dict[str, dict[str, dict]] = {}
        timings, peaks = {}, {}
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
                self.log(f"{scenario_name:>12s} {name:>18s}: {_describe(m, margins, self.scenarios[scenario_name])}")
            changes = scenario_changes(self.scenarios[scenario_name])
            if changes:
                runs = {name: None if m.diverged else m.rms_nm for name, m in metrics[scenario_name].items()}
                rate = self.scenarios[scenario_name].frame_rate_hz
                for name, entries in reconvergence(runs, changes, rate).items():
                    metrics[scenario_name][name].reconvergence = entries
        models = {key: model.info for key, model in self.classical_models.items()}
        return ExperimentResult(metrics, dict(self.checkpoints), timings, stability, _by_scenario(self.gain_scans),
                                _by_scenario(self.alpha_choices), _by_scenario(self.searches),
                                classical_models=_by_scenario(models), peak_memory_bytes=peaks)


def _by_scenario(per_controller: dict[tuple[str, str], dict]) -> dict[str, dict[str, dict]]:
    """``{(controller, scenario): value}`` regrouped as ``{scenario: {controller: value}}``, as result files hold it."""
    out: dict[str, dict[str, dict]] = {}
    for (name, scenario_name), value in per_controller.items():
        out.setdefault(scenario_name, {})[name] = value
    return out


def _describe(m: LoopMetrics, margins: dict | None, scenario: Scenario | None = None) -> str:
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
