"""An experiment: scenarios (plants) x predictors, trained once, evaluated in closed loop, written to a folder."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError, require
from eofnn.evaluation.metrics import LoopMetrics, WelchPSD, loop_metrics
from eofnn.models.build import import_class
from eofnn.models.controllers import Integrator, PseudoIntegrator, Uncorrected
from eofnn.sim.loop import run_loop
from eofnn.sim.scenario import Scenario
from eofnn.training.fit import FitResult, TrainedPredictor, fit_predictor, load_predictor
from eofnn.training.task import FIT_METHODS, OPTIMIZERS, supports_closed_form

CONTROLLERS = ("uncorrected", "pseudo_integrator", "integrator", "predictor")


@dataclass
class TrainingConfig:
    """How a predictor's training data is simulated and fitted.

    Parameters
    ----------
    frames : int
        Training frames per epoch.
    val_frames : int
        Frames of the held-out validation stream.
    sequence_frames : int
        Frames per independent turbulence realisation.
    batch_frames : int
        Frames per training batch.
    realisations : int
        Realisations simulated side by side.
    epochs : int
        Epochs of gradient descent (``fit_method: sgd``); a closed-form fit is one pass.
    optimizer : str
        ``adam``, ``sgd`` or ``lbfgs``.
    lr : float
        Learning rate.
    weight_decay : float
        Weight decay.
    integrator_gain : float
        Gain of the integrator that records closed-loop data.
    dither_nm : float
        RMS white dither added to the commands while recording closed-loop data (persistent excitation).
    refit_rounds : int
        Rounds in which the just-fitted predictor records the data of the next fit.
    seed : int
        Seed of the training (and validation) streams; evaluation uses its own stream.
    num_workers : int
        DataLoader workers.
    """

    frames: int = 20000
    val_frames: int = 2000
    sequence_frames: int = 10000
    batch_frames: int = 256
    realisations: int = 1
    epochs: int = 1
    optimizer: str = "adam"
    lr: float = 1e-3
    weight_decay: float = 0.0
    integrator_gain: float = 0.5
    dither_nm: float = 10.0
    refit_rounds: int = 0
    seed: int = 0
    num_workers: int = 0

    def __post_init__(self) -> None:
        for name in ("frames", "val_frames", "sequence_frames", "batch_frames", "realisations", "epochs"):
            value = getattr(self, name)
            require(isinstance(value, int) and value >= 1, f"training.{name}={value!r} is invalid: it must be >= 1")
        require(self.optimizer in OPTIMIZERS,
                f"training.optimizer={self.optimizer!r} is invalid: allowed are {', '.join(OPTIMIZERS)}")
        require(self.lr > 0, f"training.lr={self.lr!r} is invalid: it must be > 0")
        require(self.dither_nm >= 0, f"training.dither_nm={self.dither_nm!r} is invalid: it must be >= 0")
        require(self.refit_rounds >= 0, f"training.refit_rounds={self.refit_rounds!r} is invalid: it must be >= 0")


@dataclass
class PredictorConfig:
    """One controller of an experiment: a baseline, a predictor to train, or a saved checkpoint.

    Parameters
    ----------
    controller : str
        ``uncorrected``, ``pseudo_integrator``, ``integrator`` or ``predictor``.
    history : str
        ``open_loop`` (pseudo-open-loop values) or ``closed_loop`` (commands and residuals).
    history_length : int
        Frames of history.
    network : dict, optional
        ``{class_path: ..., init_args: {...}}`` of any ``torch.nn.Module`` mapping ``(batch, K, taps)`` to
        ``(batch, K)``; a per-actuator ``eofnn.models.linear.LinearFilter`` by default.
    fit_method : str
        ``closed_form`` (linear networks) or ``sgd``.
    alpha : float
        Ridge regularisation of the closed-form fit.
    alpha_relative : bool
        ``alpha`` relative to the mean diagonal of ``D D^T``.
    train_in : str, optional
        Name of the scenario whose plant records the training data (trained once, reused everywhere);
        by default the predictor is trained in each scenario it is evaluated in.
    training : TrainingConfig
        Training data and optimisation.
    checkpoint : str, optional
        A checkpoint from ``eofnn fit`` to evaluate instead of training.
    gain, leak : float
        Integrator gain and leak (``controller: integrator``).
    dm_gain_model : float
        DM gain the controller believes, for the pseudo-open-loop reconstruction.
    """

    controller: str = "predictor"
    history: str = "open_loop"
    history_length: int = 4
    network: dict[str, Any] | None = None
    fit_method: str = "closed_form"
    alpha: float = 1e-9
    alpha_relative: bool = True
    train_in: str | None = None
    training: TrainingConfig = field(default_factory=TrainingConfig)
    checkpoint: str | None = None
    gain: float = 0.5
    leak: float = 0.0
    dm_gain_model: float = 1.0

    def __post_init__(self) -> None:
        require(self.controller in CONTROLLERS,
                f"controller={self.controller!r} is invalid: allowed are {', '.join(CONTROLLERS)}")
        require(self.fit_method in FIT_METHODS,
                f"fit_method={self.fit_method!r} is invalid: allowed are {', '.join(FIT_METHODS)}")
        require(self.alpha >= 0, f"alpha={self.alpha!r} is invalid: it must be >= 0")
        if isinstance(self.training, dict):
            self.training = TrainingConfig(**self.training)
        if self.controller == "predictor" and self.checkpoint is None:
            HistorySpec(self.history, self.history_length)  # validates kind and length
            if self.network is not None:
                if not isinstance(self.network, dict) or "class_path" not in self.network:
                    raise ConfigError(f"network={self.network!r} is invalid: give class_path and init_args")
                import_class(self.network["class_path"])
        if self.controller == "integrator":
            Integrator(self.gain, self.leak)


@dataclass
class EvaluationConfig:
    """How controllers are evaluated in closed loop.

    Parameters
    ----------
    frames : int
        Frames per run.
    settle_frames : int
        Frames discarded at the start (the loop settling) before statistics.
    realisations : int
        Independent turbulence realisations run side by side.
    seed : int
        Seed of the test stream (a stream of its own: never shared with training).
    strehl_wavelength_m : float
        Wavelength of the Maréchal Strehl, in metres.
    divergence_factor : float
        A residual above this times the turbulence RMS counts as diverged.
    psd_segment_frames : int
        Segment length of the residual PSD.
    """

    frames: int = 5000
    settle_frames: int = 500
    realisations: int = 1
    seed: int = 1
    strehl_wavelength_m: float = 1.65e-6
    divergence_factor: float = 10.0
    psd_segment_frames: int = 1024

    def __post_init__(self) -> None:
        require(self.frames > self.settle_frames >= 0,
                f"evaluation.frames={self.frames!r} must exceed settle_frames={self.settle_frames!r} >= 0")
        require(self.realisations >= 1, f"evaluation.realisations={self.realisations!r} is invalid: it must be >= 1")
        require(self.strehl_wavelength_m > 0,
                f"evaluation.strehl_wavelength_m={self.strehl_wavelength_m!r} is invalid: it must be > 0 (metres)")
        require(self.psd_segment_frames >= 8,
                f"evaluation.psd_segment_frames={self.psd_segment_frames!r} is invalid: it must be >= 8")


@dataclass
class ExperimentResult:
    """Metrics by scenario and predictor, and where the checkpoints went."""

    metrics: dict[str, dict[str, LoopMetrics]]
    checkpoints: dict[str, str] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "scenarios": {s: {p: m.summary() for p, m in preds.items()} for s, preds in self.metrics.items()},
            "checkpoints": self.checkpoints,
            "timings_s": self.timings_s,
        }


def fit_from_config(scenario: Scenario, cfg: PredictorConfig, checkpoint_path: str | Path | None = None,
                    overwrite: bool = False, progress: bool = False) -> FitResult:
    """Train the predictor described by ``cfg`` on telemetry simulated in ``scenario``."""
    t = cfg.training
    return fit_predictor(
        scenario, HistorySpec(cfg.history, cfg.history_length, scenario.delay_frames), cfg.network,
        fit_method=cfg.fit_method, alpha=cfg.alpha, alpha_relative=cfg.alpha_relative, optimizer=t.optimizer,
        lr=t.lr, weight_decay=t.weight_decay, max_epochs=t.epochs, train_frames=t.frames, val_frames=t.val_frames,
        sequence_frames=t.sequence_frames, batch_frames=t.batch_frames, n_realisations=t.realisations, seed=t.seed,
        integrator_gain=t.integrator_gain, dither_nm=t.dither_nm, refit_rounds=t.refit_rounds,
        num_workers=t.num_workers, checkpoint_path=checkpoint_path, overwrite=overwrite, progress=progress,
    )


def check_output_dir(out: str | Path | None, overwrite: bool) -> Path | None:
    """Refuse a non-empty output folder unless ``overwrite`` (nothing a user wrote is lost unasked)."""
    if out is None:
        return None
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"out={str(out)!r} is a file, not a folder")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise ConfigError(f"out={str(out)!r} is not empty: choose another folder or pass --overwrite true")
    return out


def build_scenarios(base: Scenario, scenarios: dict[str, dict[str, Any]]) -> dict[str, Scenario]:
    """The base scenario with each entry's model errors (``{}`` is the nominal plant)."""
    require(len(scenarios) >= 1, "scenarios is empty: give at least one, e.g. nominal: {}")
    out = {}
    for name, errors in scenarios.items():
        try:
            out[name] = base.with_model_errors(**dict(base.model_errors, **(errors or {})))
        except ConfigError as err:
            raise ConfigError(f"scenario {name!r}: {err}") from None
    return out


class Experiment:
    """Validates everything up front, then trains, evaluates and collects metrics.

    Parameters
    ----------
    scenario : Scenario
        Telescope, atmosphere, frame rate and delay shared by all scenarios.
    scenarios : dict
        Scenario name -> model errors.
    predictors : dict
        Predictor name -> :class:`PredictorConfig`.
    evaluation : EvaluationConfig
        Closed-loop evaluation settings.
    checkpoint_dir : path, optional
        Where trained predictors are saved.
    progress : bool or None
        Progress bars (``None``: only on a terminal).
    """

    def __init__(self, scenario: Scenario, scenarios: dict[str, dict[str, Any]],
                 predictors: dict[str, PredictorConfig], evaluation: EvaluationConfig,
                 checkpoint_dir: str | Path | None = None, progress: bool | None = None, log=print) -> None:
        require(len(predictors) >= 1, "predictors is empty: give at least one")
        self.scenarios = build_scenarios(scenario, scenarios)
        self.predictors = {name: cfg if isinstance(cfg, PredictorConfig) else PredictorConfig(**cfg)
                           for name, cfg in predictors.items()}
        self.evaluation = evaluation
        self.checkpoint_dir = Path(checkpoint_dir) if checkpoint_dir is not None else None
        self.progress, self.log = progress, log
        self._trained: dict[tuple[str, str], TrainedPredictor] = {}
        self.checkpoints: dict[str, str] = {}
        self._loaded: dict[str, TrainedPredictor] = {}
        self._validate()

    def _validate(self) -> None:
        for name, cfg in self.predictors.items():
            if cfg.controller != "predictor":
                continue
            if cfg.train_in is not None and cfg.train_in not in self.scenarios:
                raise ConfigError(f"predictor {name!r}: train_in={cfg.train_in!r} is not a scenario: allowed are "
                                  f"{', '.join(self.scenarios)}")
            if cfg.checkpoint is not None:
                predictor = load_predictor(cfg.checkpoint)
                for _scenario_name, scenario in self.scenarios.items():
                    predictor.check_fits(scenario, f"predictor {name!r}: checkpoint {cfg.checkpoint!r}")
                self._loaded[name] = predictor
            elif cfg.fit_method == "closed_form" and cfg.network is not None:
                cls = import_class(cfg.network["class_path"])
                if not supports_closed_form(cls):
                    raise ConfigError(f"predictor {name!r}: fit_method='closed_form' needs a linear network; "
                                      f"{cls.__name__} has no features()/load_solution(): use fit_method: sgd")

    def predictor(self, name: str, scenario_name: str) -> TrainedPredictor:
        """The trained predictor ``name`` for evaluation in ``scenario_name`` (trained on first use)."""
        cfg = self.predictors[name]
        if name in self._loaded:
            return self._loaded[name]
        train_in = cfg.train_in or scenario_name
        key = (name, train_in)
        if key not in self._trained:
            scenario = self.scenarios[train_in]
            path = None
            if self.checkpoint_dir is not None:
                path = self.checkpoint_dir / f"{name}__{train_in}.ckpt"
            self.log(f"training {name} in scenario {train_in} ({cfg.history}, p={cfg.history_length}, {cfg.fit_method})")
            result = fit_from_config(scenario, cfg, path, overwrite=True, progress=bool(self.progress))
            self._trained[key] = result.predictor
            if path is not None:
                self.checkpoints[f"{name}/{train_in}"] = str(path)
        return self._trained[key]

    def controller(self, name: str, scenario_name: str):
        cfg = self.predictors[name]
        if cfg.controller == "uncorrected":
            return Uncorrected()
        if cfg.controller == "pseudo_integrator":
            return PseudoIntegrator()
        if cfg.controller == "integrator":
            return Integrator(cfg.gain, cfg.leak)
        return self.predictor(name, scenario_name).controller(cfg.dm_gain_model)

    def evaluate(self, name: str, scenario_name: str) -> LoopMetrics:
        """Closed-loop metrics of predictor ``name`` in scenario ``scenario_name`` on the test stream."""
        ev, scenario = self.evaluation, self.scenarios[scenario_name]
        controller = self.controller(name, scenario_name)
        psd = WelchPSD(ev.psd_segment_frames, scenario.frame_rate_hz, ev.settle_frames)
        result = run_loop(scenario.turbulence(ev.seed, "test", ev.realisations), scenario.plant, controller,
                          ev.frames, noise_seed=ev.seed, record=(), divergence_factor=ev.divergence_factor,
                          progress=self.progress, on_chunk=psd)
        return loop_metrics(result, ev.settle_frames, ev.strehl_wavelength_m, psd)

    def run(self) -> ExperimentResult:
        metrics: dict[str, dict[str, LoopMetrics]] = {}
        timings = {}
        for scenario_name in self.scenarios:
            metrics[scenario_name] = {}
            for name in self.predictors:
                start = time.perf_counter()
                m = self.evaluate(name, scenario_name)
                timings[f"{scenario_name}/{name}"] = round(time.perf_counter() - start, 3)
                metrics[scenario_name][name] = m
                shown = f"diverged at frame {m.diverged_frame}" if m.diverged else f"{m.median_rms_nm:.4g} nm"
                self.log(f"{scenario_name:>12s} {name:>18s}: median RMS {shown}")
        return ExperimentResult(metrics, dict(self.checkpoints), timings)


def save_timeseries(result: ExperimentResult, path: Path) -> None:
    """Per-frame RMS and PSDs of every run, for re-plotting without re-running."""
    data = {}
    for s, preds in result.metrics.items():
        for p, m in preds.items():
            data[f"{s}/{p}/rms_nm"] = torch.tensor(m.rms_nm).numpy()
            data[f"{s}/{p}/psd_freq_hz"] = torch.tensor(m.psd_freq_hz).numpy()
            data[f"{s}/{p}/psd_nm2_per_hz"] = torch.tensor(m.psd_nm2_per_hz).numpy()
    import numpy as np

    np.savez_compressed(path, **data)


def write_metrics(result: ExperimentResult, path: Path, extra: dict | None = None) -> None:
    payload = result.to_json()
    payload.update(extra or {})
    path.write_text(json.dumps(payload, indent=2))


__all__ = ["EvaluationConfig", "Experiment", "ExperimentResult", "PredictorConfig", "TrainingConfig", "asdict"]
