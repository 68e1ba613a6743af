"""Fitting a predictor: a function beside the model that takes grouped options and returns a small result (BoTorch style).

``fit_predictor(scenario, history, history_length, network, data=..., optimization=...)`` simulates the training
telemetry in ``scenario`` (:class:`~eofnn.data.stream.DataConfig`), fits the network
(:class:`~eofnn.training.task.OptimizationConfig`) and returns a :class:`FitResult`. Two steps, both explicit:

1. *closed form* (linear networks): one streamed pass of ridge regression, :func:`~eofnn.training.ridge.fit_closed_form`,
   then Lightning's ``validate`` for the held-out loss;
2. *SGD* (any network): Lightning's ``fit``.
"""

from __future__ import annotations

import copy
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import lightning as L
from torch import nn

from eofnn.control.baselines import Dithered, Integrator
from eofnn.control.predictive import PredictiveController
from eofnn.data.history import HistorySpec
from eofnn.data.stream import DataConfig, LoopDataModule
from eofnn.errors import CheckpointError, CollinearityWarning, ConfigError
from eofnn.outputs import check_output_file, staged_file
from eofnn.sim.loop import Controller
from eofnn.sim.scenario import Scenario
from eofnn.training.alpha import MarginFunction, RidgePath
from eofnn.training.ridge import ClosedFormFit, fit_closed_form, supports_closed_form
from eofnn.training.search import check_search, run_search
from eofnn.training.task import OptimizationConfig, PredictorTask, check_fit, resolve_normalize

DEFAULT_NETWORK = {"class_path": "eofnn.models.linear.LinearFilter", "init_args": {}}


@dataclass
class TrainedPredictor:
    """A predictor ready for the loop: its network, the history it reads, and how it was made."""

    network: nn.Module
    spec: HistorySpec
    network_config: dict
    n_actuators: int
    info: dict = field(default_factory=dict)
    #: The ridge path this predictor's alpha was chosen on (``alpha: auto``; not saved in checkpoints): the filter
    #: at any other alpha of it, for performance-robustness curves.
    ridge_path: RidgePath | None = field(default=None, repr=False)

    @property
    def dm_gain_model(self) -> float:
        """The DM gain this predictor's pseudo-open-loop reconstruction assumes by default: identified from telemetry
        when it learnt from telemetry, 1 (the nominal DM) otherwise."""
        return float(self.info.get("dm_gain_model", 1.0))

    def controller(self, dm_gain_model: float = 1.0) -> PredictiveController:
        """The loop-side controller that runs this predictor (``dm_gain_model``: the DM gain it believes)."""
        return PredictiveController(self.network, self.spec, dm_gain_model)

    def check_fits(self, scenario: Scenario, where: str = "checkpoint", history_length: int | None = None) -> None:
        """One-line error unless this predictor can run in ``scenario`` (actuators, delay) with ``history_length``."""
        n = scenario.grid.n_actuators
        if self.n_actuators != n:
            raise CheckpointError(f"{where} was trained for n_actuators={self.n_actuators} but the scenario has "
                                  f"n_actuators={n}")
        if self.spec.delay_frames != scenario.plant.delay_frames:
            raise CheckpointError(f"{where} was trained for delay_frames={self.spec.delay_frames} but the scenario "
                                  f"has delay_frames={scenario.plant.delay_frames}")
        if history_length is not None and history_length != self.spec.history_length:
            raise CheckpointError(f"{where} has history_length={self.spec.history_length} but "
                                  f"history_length={history_length} was asked for")


@dataclass
class FitResult:
    """Outcome of :func:`fit_predictor`: the predictor, its losses (nm²) per round, and the checkpoint path."""

    predictor: TrainedPredictor
    train_loss: float | None
    val_loss: float | None
    rounds: list[dict] = field(default_factory=list)
    checkpoint: Path | None = None


def recording_controller(spec: HistorySpec, data: DataConfig) -> Controller | None:
    """The controller that records closed-loop training data: an integrator plus white dither (none for open loop)."""
    if spec.kind != "closed_loop":
        return None
    if data.dither_nm == 0:
        warnings.warn("closed-loop data recorded without excitation (data.dither_nm = 0): the controller law ties y "
                      "to past eps, so the regressors are collinear; set a dither > 0", CollinearityWarning,
                      stacklevel=3)
    return Dithered(Integrator(data.integrator_gain, 0.0), data.dither_nm, data.seed)


def fit_predictor(
    scenario: Scenario,
    history: str = "open_loop",
    history_length: int = 4,
    network: dict[str, Any] | None = None,
    *,
    data: DataConfig | None = None,
    optimization: OptimizationConfig | None = None,
    checkpoint_path: str | Path | None = None,
    overwrite: bool = False,
    progress: bool = False,
    margin: MarginFunction | None = None,
) -> FitResult:
    """Train a predictor on telemetry simulated in ``scenario``.

    Closed-loop histories are recorded with an integrator (``data.integrator_gain``) plus ``data.dither_nm`` of
    white dither; with ``data.refit_rounds > 0`` the just-fitted predictor (plus the same dither) records the data
    of the next round, and the fit is redone from scratch on it.

    Parameters
    ----------
    scenario : Scenario
        Where training data is simulated (its plant included: closed-loop EOF learns that plant, and the
        history's delay is the plant's).
    history : {"open_loop", "closed_loop"}
        Pseudo-open-loop values, or past commands and residuals.
    history_length : int
        Frames of history.
    network : dict, optional
        ``{"class_path": ..., "init_args": {...}}``; a per-actuator :class:`~eofnn.models.linear.LinearFilter`
        by default.
    data : DataConfig
        How the training and validation telemetry is simulated.
    optimization : OptimizationConfig
        Fit method, ridge, optimiser and accelerator.
    checkpoint_path : path, optional
        Where to write the Lightning checkpoint; an existing file is kept unless ``overwrite``.
    progress : bool
        Lightning's progress bar.
    margin : callable, optional
        :data:`~eofnn.training.alpha.MarginFunction`, for an ``optimization.select`` constraint on ``alpha: auto``
        (built by the caller, which knows the stability analysis).
    """
    data = data or DataConfig()
    optimization = optimization or OptimizationConfig()
    spec = HistorySpec.from_scenario(history, history_length, scenario)
    if checkpoint_path is not None:
        checkpoint_path = check_output_file(checkpoint_path, overwrite, "checkpoint")
    network_config = network or DEFAULT_NETWORK
    grid = {"diameter_m": scenario.grid.diameter_m, "n_across": scenario.grid.n_across,
            "obstruction": scenario.grid.obstruction}
    # Network initialisation and SGD draw from torch's global generator: seed it, so a fit is reproducible.
    L.seed_everything(data.seed, workers=True, verbose=False)
    info = {"scenario": scenario.to_dict(), "data": asdict(data)}
    task = PredictorTask(network_config, scenario.grid.n_actuators, spec.to_dict(), grid,
                         resolve_normalize(network_config, asdict(optimization)), info)
    net = task.network
    if optimization.fit_method == "closed_form" and not supports_closed_form(net):
        raise ConfigError(f"optimization.fit_method='closed_form' needs a linear network; {type(net).__name__} has no "
                          "features()/load_solution(): use optimization.fit_method: sgd")
    data_controller = recording_controller(spec, data)
    rounds = []
    trainer = ridge_path = None
    for round_index in range(data.refit_rounds + 1):
        if round_index > 0:
            data_controller = Dithered(PredictiveController(copy.deepcopy(net), spec), data.dither_nm,
                                       data.seed + round_index)
        datamodule = LoopDataModule(scenario, spec, replace(data, seed=data.seed + 1000 * round_index), data_controller)
        trainer = make_trainer(optimization, progress)
        try:
            if optimization.fit_method == "closed_form":
                # The loop the filter is made for: closed-loop EOF learns this plant's DM; open-loop EOF believes 1.
                plant_gain = scenario.plant.dm_gain if spec.kind == "closed_loop" else 1.0
                solved = solve_closed_form(net, datamodule.train_dataloader(), datamodule.val_dataloader(),
                                           optimization, bind_margin(margin, net, spec, plant_gain, 1.0))
                metrics = {"train_loss": solved.train_loss, "condition": solved.condition, "alpha": solved.alpha}
                if solved.choice is not None:
                    info["alpha_choice"] = solved.choice.summary()
                    task.hparams["info"] = info
                ridge_path = solved.choice.path if solved.choice is not None else None
                metrics.update(trainer.validate(task, dataloaders=datamodule.val_dataloader(), verbose=False,
                                                weights_only=True)[0])
            elif optimization.search is not None:
                task, trainer, searched = run_search(
                    check_search(optimization.search, optimization.lr), network_config, optimization,
                    lambda net_cfg, opt: PredictorTask(net_cfg, scenario.grid.n_actuators, spec.to_dict(), grid,
                                                       resolve_normalize(net_cfg, asdict(opt)), info),
                    lambda t, tr, dm=datamodule: tr.fit(t, datamodule=dm, weights_only=True),
                    lambda opt, callbacks: make_trainer(opt, progress, callbacks), data.seed, data.frames)
                net, network_config = task.network, task.hparams.network
                info["search"] = searched
                task.hparams["info"] = info
                metrics = {"val_loss": searched["chosen"]["val_loss"], "lr": searched["chosen"]["lr"]}
            else:
                trainer.fit(task, datamodule=datamodule, weights_only=True)
                metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
        except SystemExit:
            # Lightning answers Ctrl-C inside fit/validate with its own shutdown and sys.exit(1): it is an interruption.
            raise KeyboardInterrupt from None
        rounds.append({"round": round_index, **metrics})
    last = rounds[-1]
    sgd = optimization.fit_method != "closed_form"
    check_fit(task, last.get("train_loss"), last.get("val_loss"), datamodule.val_dataloader() if sgd else None)
    net.eval()
    predictor = TrainedPredictor(net, spec, network_config, scenario.grid.n_actuators, info, ridge_path)
    if checkpoint_path is not None:
        with staged_file(checkpoint_path, overwrite) as partial:
            trainer.save_checkpoint(partial)
    return FitResult(predictor, last.get("train_loss"), last.get("val_loss"), rounds, checkpoint_path)


def solve_closed_form(network: nn.Module, train, validation, optimization: OptimizationConfig,
                      margin: MarginFunction | None = None) -> ClosedFormFit:
    """The closed-form fit of ``optimization``: its fixed alpha, or (``alpha: auto``) the alpha chosen on
    ``validation`` under its ``select`` constraint (checked with ``margin``)."""
    alpha = optimization.alpha_for(validation is not None)
    return fit_closed_form(network, train, alpha, optimization.alpha_relative,
                           validation=validation if alpha == "auto" else None, alpha_path=optimization.alpha_path,
                           interval=optimization.dm_gain_interval, margin=margin)


def bind_margin(margin: MarginFunction | None, network: nn.Module, spec: HistorySpec, plant_dm_gain: float,
                dm_gain_model: float):
    """``weights -> interval``: ``margin`` for this network, history and loop (``None`` when no margin is given)."""
    if margin is None:
        return None
    return lambda weights: margin(network, weights, spec, plant_dm_gain, dm_gain_model)


def make_trainer(optimization: OptimizationConfig, progress: bool, callbacks: list | None = None) -> L.Trainer:
    """The Lightning trainer of a fit: one epoch for a closed-form fit (validation only), no logger of its own."""
    epochs = 1 if optimization.fit_method == "closed_form" else optimization.epochs
    return L.Trainer(max_epochs=epochs, accelerator=optimization.accelerator, devices=1, logger=False,
                     enable_checkpointing=False, enable_progress_bar=progress, enable_model_summary=False,
                     num_sanity_val_steps=0, deterministic=True, callbacks=callbacks)
