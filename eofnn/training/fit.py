"""Fitting a predictor: a function beside the model, returning a small result object (BoTorch style)."""

from __future__ import annotations

import copy
import logging
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import nn

from eofnn.data.history import HistorySpec
from eofnn.data.stream import LoopDataModule, default_data_controller
from eofnn.errors import CheckpointError, ConfigError
from eofnn.models.build import build_network
from eofnn.models.controllers import Dithered
from eofnn.models.predictive import PredictiveController
from eofnn.sim.scenario import Scenario
from eofnn.training.task import PredictorTask


@dataclass
class TrainedPredictor:
    """A predictor ready for the loop: its network, the history it reads, and how it was made."""

    network: nn.Module
    spec: HistorySpec
    network_config: dict
    grid: dict
    info: dict = field(default_factory=dict)

    @property
    def n_actuators(self) -> int:
        return int(self.info["n_actuators"])

    def controller(self, dm_gain_model: float = 1.0) -> PredictiveController:
        return PredictiveController(self.network, self.spec, dm_gain_model)

    def check_fits(self, scenario: Scenario, where: str = "checkpoint", history_length: int | None = None) -> None:
        """One-line error unless this predictor can run in ``scenario`` (actuators, delay) with ``history_length``."""
        n = scenario.grid.n_actuators
        if self.n_actuators != n:
            raise CheckpointError(f"{where} was trained for n_actuators={self.n_actuators} but the scenario has "
                                  f"n_actuators={n}")
        if self.spec.delay_frames != scenario.delay_frames:
            raise CheckpointError(f"{where} was trained for delay_frames={self.spec.delay_frames} but the scenario "
                                  f"has delay_frames={scenario.delay_frames}")
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


def fit_predictor(
    scenario: Scenario,
    spec: HistorySpec,
    network: dict[str, Any] | None = None,
    *,
    fit_method: str = "closed_form",
    alpha: float = 1e-9,
    alpha_relative: bool = True,
    optimizer: str = "adam",
    lr: float = 1e-3,
    weight_decay: float = 0.0,
    max_epochs: int = 1,
    train_frames: int = 20000,
    val_frames: int = 2000,
    sequence_frames: int = 10000,
    batch_frames: int = 256,
    n_realisations: int = 1,
    seed: int = 0,
    integrator_gain: float = 0.5,
    dither_nm: float = 10.0,
    refit_rounds: int = 0,
    num_workers: int = 0,
    checkpoint_path: str | Path | None = None,
    overwrite: bool = False,
    progress: bool = False,
    log_dir: str | Path | None = None,
) -> FitResult:
    """Train a predictor on telemetry simulated in ``scenario``.

    Closed-loop histories are recorded with an integrator (``integrator_gain``) plus ``dither_nm`` of white
    dither; with ``refit_rounds > 0`` the just-fitted predictor (plus the same dither) records the data of the
    next round, and the fit is redone from scratch on it.

    Parameters
    ----------
    scenario : Scenario
        Where training data is simulated (its plant included: closed-loop EOF learns that plant).
    spec : HistorySpec
        History kind, length and delay (the delay must match the scenario's).
    network : dict
        ``{"class_path": ..., "init_args": {...}}``; a per-actuator :class:`~eofnn.models.linear.LinearFilter`
        by default.
    fit_method, alpha, alpha_relative, optimizer, lr, weight_decay, max_epochs
        See :class:`~eofnn.training.task.PredictorTask`; ``max_epochs`` applies to SGD (a closed-form fit is one pass).
    train_frames, val_frames, sequence_frames, batch_frames, n_realisations, seed, num_workers
        See :class:`~eofnn.data.stream.LoopDataModule`.
    checkpoint_path : path, optional
        Where to write the Lightning checkpoint; an existing file is kept unless ``overwrite``.
    """
    if spec.delay_frames != scenario.delay_frames:
        raise ConfigError(f"history delay_frames={spec.delay_frames} differs from the scenario's "
                          f"delay_frames={scenario.delay_frames}")
    if checkpoint_path is not None:
        checkpoint_path = Path(checkpoint_path)
        if checkpoint_path.exists() and not overwrite:
            raise FileExistsError(f"checkpoint {checkpoint_path} exists: pass overwrite to replace it")
    network_config = network or {"class_path": "eofnn.models.linear.LinearFilter", "init_args": {}}
    grid = {"diameter_m": scenario.grid.diameter_m, "n_across": scenario.grid.n_across,
            "obstruction": scenario.grid.obstruction}
    # Network initialisation and SGD draw from torch's global generator: seed it, so a fit is reproducible.
    L.seed_everything(seed, workers=True, verbose=False)
    net = build_network(network_config, scenario.grid.n_actuators, spec.n_taps, grid, spec.kind, spec.delay_frames)
    info = {"n_actuators": scenario.grid.n_actuators, "scenario": scenario.to_dict(), "fit_method": fit_method,
            "train_frames": train_frames, "seed": seed, "refit_rounds": refit_rounds, "dither_nm": dither_nm}
    task = PredictorTask(net, fit_method, alpha, alpha_relative, optimizer, lr, weight_decay,
                         spec=spec.to_dict(), network_config=network_config, grid=grid, info=info)
    data_controller = default_data_controller(integrator_gain, 0.0, dither_nm, seed) if spec.kind == "closed_loop" \
        else None
    rounds = []
    trainer = None
    for round_index in range(refit_rounds + 1):
        if round_index > 0:
            data_controller = Dithered(PredictiveController(copy.deepcopy(net), spec), dither_nm, seed + round_index)
        datamodule = LoopDataModule(scenario, spec, train_frames, val_frames, sequence_frames, batch_frames,
                                    n_realisations, seed + 1000 * round_index, data_controller, num_workers)
        trainer = _trainer(1 if fit_method == "closed_form" else max_epochs, progress, log_dir)
        with warnings.catch_warnings():
            # A closed-form fit has no optimiser by design; Lightning says so on every fit.
            warnings.filterwarnings("ignore", message=".*configure_optimizers` returned `None`.*")
            trainer.fit(task, datamodule=datamodule)
        metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
        rounds.append({"round": round_index, **metrics})
    predictor = TrainedPredictor(net, spec, network_config, grid, info)
    if checkpoint_path is not None:
        checkpoint_path.parent.mkdir(parents=True, exist_ok=True)
        trainer.save_checkpoint(checkpoint_path)
    last = rounds[-1]
    return FitResult(predictor, last.get("train_loss"), last.get("val_loss"), rounds, checkpoint_path)


def _trainer(max_epochs: int, progress: bool, log_dir) -> L.Trainer:
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.pytorch.accelerators.cuda",
                 "lightning.pytorch.trainer.connectors.checkpoint_connector"):
        logging.getLogger(name).setLevel(logging.WARNING)
    logger = L.pytorch.loggers.CSVLogger(str(log_dir), name="fit") if log_dir is not None else False
    return L.Trainer(max_epochs=max_epochs, accelerator="cpu", devices=1, logger=logger, enable_checkpointing=False,
                     enable_progress_bar=progress, enable_model_summary=False, num_sanity_val_steps=0,
                     deterministic=True)


def load_predictor(path: str | Path, scenario: Scenario | None = None,
                   history_length: int | None = None) -> TrainedPredictor:
    """Rebuild a predictor from a checkpoint written by :func:`fit_predictor` (``weights_only`` loading).

    With ``scenario`` (and ``history_length``), also check that it fits them, with a one-line error if not.
    """
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises UnpicklingError, EOFError, RuntimeError... for files that are not checkpoints
        raise CheckpointError(f"checkpoint {str(path)!r} is not an eofnn predictor checkpoint "
                              f"({type(err).__name__})") from None
    try:
        hp = ckpt["hyper_parameters"]
        spec = HistorySpec(**hp["spec"])
        info = dict(hp["info"])
        network = build_network(hp["network_config"], info["n_actuators"], spec.n_taps, hp["grid"], spec.kind,
                                spec.delay_frames)
        state = {k.removeprefix("network."): v for k, v in ckpt["state_dict"].items() if k.startswith("network.")}
        network.load_state_dict(state)
    except (KeyError, TypeError, RuntimeError, ValueError) as err:
        if isinstance(err, ConfigError):
            raise
        raise CheckpointError(f"checkpoint {str(path)!r} is not an eofnn predictor checkpoint "
                              f"({type(err).__name__}: {str(err).splitlines()[0]})") from None
    network.eval()
    predictor = TrainedPredictor(network, spec, hp["network_config"], hp["grid"], info)
    if scenario is not None:
        predictor.check_fits(scenario, f"checkpoint {str(path)!r}", history_length)
    return predictor
