"""Fitting a predictor: one solve for closed form and SGD, from simulator truth or from telemetry (BoTorch style).

``fit_predictor(scenario, history, history_length, network, data=..., optimization=..., output=...)`` simulates the
training telemetry in ``scenario`` (:class:`~eofnn.data.stream.DataConfig`), fits the network
(:class:`~eofnn.training.task.OptimizationConfig`) and returns a :class:`FitResult`;
:func:`eofnn.training.from_telemetry.fit_from_telemetry` does the same from recorded telemetry. Both build their task
with :func:`new_task`, fit it with :func:`solve` (the one place that tells the two methods apart) and close with
:meth:`Solved.result`:

1. *closed form* (linear networks): one streamed pass of ridge regression, :func:`~eofnn.training.ridge.fit_closed_form`,
   then Lightning's ``validate`` for the held-out loss;
2. *SGD* (any network): Lightning's ``fit`` (or a budgeted search, :mod:`eofnn.training.search`);
3. *through the loop* (linear networks): the closed-form fit, then Lightning's ``fit`` on the closed-loop residual
   of the same frames (:mod:`eofnn.training.through_loop`).
"""

from __future__ import annotations

import contextlib
import copy
import logging
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import lightning as L
from torch import nn
from torch.utils.data import DataLoader

from eofnn.control.baselines import Dithered, Integrator
from eofnn.control.predictive import PredictiveController, believed_dm_gain
from eofnn.data.history import HistorySpec
from eofnn.data.stream import DataConfig, LoopDataModule, open_loop_recorded
from eofnn.errors import CheckpointError, CollinearityWarning, ConfigError, DivergedError
from eofnn.outputs import check_output_file, staged_file
from eofnn.sim.layout import layout_to_dict
from eofnn.sim.loop.runner import Controller
from eofnn.sim.scenario import Scenario
from eofnn.training.alpha import MarginFunction, RidgePath
from eofnn.training.conditions import scenario_conditions
from eofnn.training.noise import noise_term
from eofnn.training.ridge import solve_closed_form, supports_closed_form
from eofnn.training.search import check_search, run_search
from eofnn.training.task import OptimizationConfig, PredictorTask, check_fit, resolve_normalize
from eofnn.training.through_loop import LoopData, loop_data, train_through_loop

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

    def controller(self, dm_gain_model: float | None = None) -> PredictiveController:
        """The loop-side controller that runs this predictor (``dm_gain_model``: the DM gain it believes; unset, its
        own, :func:`~eofnn.control.predictive.believed_dm_gain`)."""
        return PredictiveController(self.network, self.spec, believed_dm_gain(dm_gain_model, self))

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
    """Outcome of a fit, from simulator truth or from telemetry: the predictor (its ``info`` says how it was made:
    for a telemetry fit the DM model it was fitted through), its losses (nm²; of the last round), the metrics of each
    round of recorded data (simulator truth), and the checkpoint path."""

    predictor: TrainedPredictor
    train_loss: float | None
    val_loss: float | None
    rounds: list[dict] = field(default_factory=list)
    checkpoint: Path | None = None

    @property
    def network(self) -> nn.Module:
        return self.predictor.network

    @property
    def spec(self) -> HistorySpec:
        return self.predictor.spec

    @property
    def info(self) -> dict:
        return self.predictor.info

    def controller(self, dm_gain_model: float | None = None) -> PredictiveController:
        """Loop-side controller (:meth:`TrainedPredictor.controller`): open loop reconstructs POL values with the DM
        gain the fit assumed."""
        return self.predictor.controller(dm_gain_model)


@dataclass
class FitOutput:
    """What a fit writes besides its result: a checkpoint at ``checkpoint_path`` (an existing file is kept unless
    ``overwrite``), and Lightning's progress bar (``progress``)."""

    checkpoint_path: str | Path | None = None
    overwrite: bool = False
    progress: bool = False

    def checked(self) -> FitOutput:
        """This output, its checkpoint path checked up front (one line when it may not be written)."""
        if self.checkpoint_path is None:
            return self
        return replace(self, checkpoint_path=check_output_file(self.checkpoint_path, self.overwrite, "checkpoint"))


@dataclass
class FitData:
    """What one solve learns from: ``train`` and held-out ``validation`` (optional) ``(history, target)`` batches (a
    DataLoader, or any iterable of ready batches), the frames one pass over ``train`` holds (a search's budget), and
    the same streams as windows of the loop (training through the loop; simulator truth only)."""

    train: Iterable
    validation: Iterable | None
    frames: int
    loop: LoopData | None = None


def recording_controller(spec: HistorySpec, data: DataConfig, scenario: Scenario | None = None) -> Controller | None:
    """The controller that records closed-loop training data, and open-loop data in the plants of a
    ``data.plant_range`` or through ``scenario``'s pyramid (:func:`~eofnn.data.stream.open_loop_recorded`): an
    integrator plus white dither (none for other open-loop data)."""
    recorded = data.plant_range if scenario is None else open_loop_recorded(scenario, data)
    if spec.kind != "closed_loop" and not recorded:
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
    output: FitOutput | None = None,
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
    output : FitOutput
        The checkpoint to write (an existing file is kept unless ``overwrite``) and Lightning's progress bar.
    margin : callable, optional
        :data:`~eofnn.training.alpha.MarginFunction`, for an ``optimization.select`` constraint on ``alpha: auto``
        (built by the caller, which knows the stability analysis).
    """
    data = data or DataConfig()
    optimization = optimization or OptimizationConfig()
    spec = HistorySpec.from_scenario(history, history_length, scenario)
    output = (output or FitOutput()).checked()
    info = {"scenario": scenario.to_dict(), "data": asdict(data), "conditions": scenario_conditions(scenario).to_dict()}
    task = new_task(network or DEFAULT_NETWORK, scenario.grid.n_actuators, spec, layout_to_dict(scenario.grid),
                    optimization, info, data.seed)
    # The loop the filter is made for: closed-loop EOF learns this plant's DM; open-loop EOF believes 1.
    plant_gain = scenario.plant.dm_gain if spec.kind == "closed_loop" else 1.0
    data_controller = recording_controller(spec, data, scenario)
    rounds = []
    for round_index in range(data.refit_rounds + 1):
        if round_index > 0:
            data_controller = Dithered(PredictiveController(copy.deepcopy(task.network), spec), data.dither_nm,
                                       data.seed + round_index)
        round_data = replace(data, seed=data.seed + 1000 * round_index)
        datamodule = LoopDataModule(scenario, spec, round_data, data_controller)
        try:
            loop = loop_data(datamodule, round_data, optimization) if optimization.fit_method == "closed_loop" else None
            solved = solve(task, FitData(datamodule.train_dataloader(), datamodule.val_dataloader(), data.frames, loop),
                           optimization, output=output, seed=data.seed,
                           margin=bind_margin(margin, task.network, spec, plant_gain, 1.0))
        except DivergedError as err:
            if round_index == 0:
                raise
            # The previous round's filter cannot hold the loop it would record in: keep it, say so, stop refitting.
            warnings.warn(f"data.refit_rounds: round {round_index} skipped, the round-{round_index - 1} fit cannot "
                          f"record it ({err}); the round-{round_index - 1} fit is kept", stacklevel=2)
            rounds.append({"round": round_index, "skipped": str(err)})
            break
        task = solved.task
        rounds.append({"round": round_index, **solved.metrics})
    return solved.result(output, rounds)


def new_task(network: dict, n_actuators: int, spec: HistorySpec, grid: dict | None,
             optimization: OptimizationConfig, info: dict, seed: int) -> PredictorTask:
    """The task of a fit, its network initialised from ``seed`` (a fit is reproducible); one line when a closed-form
    fit is asked of a network that has none."""
    # Network initialisation and SGD draw from torch's global generator: seed it, so a fit is reproducible.
    L.seed_everything(seed, workers=True, verbose=False)
    task = PredictorTask(network, n_actuators, spec.to_dict(), grid, resolve_normalize(network, asdict(optimization)),
                         info)
    if optimization.fit_method in ("closed_form", "closed_loop") and not supports_closed_form(task.network):
        raise ConfigError(f"optimization.fit_method={optimization.fit_method!r} needs a linear network; "
                          f"{type(task.network).__name__} has no features()/load_solution(): use "
                          "optimization.fit_method: sgd")
    return task


@dataclass
class Solved:
    """One :func:`solve`: the task (a search may have replaced it), the trainer that holds it (``None`` when none was
    needed), the metrics of the solve (losses in nm², alpha, ...), what it learnt from, and the ridge path of an
    ``alpha: auto`` choice."""

    task: PredictorTask
    trainer: L.Trainer | None
    metrics: dict
    data: FitData
    ridge_path: RidgePath | None = None

    def result(self, output: FitOutput, rounds: list[dict] | None = None) -> FitResult:
        """The fit's result: non-finite losses refused (and a warning when gradient descent did not beat the trivial
        predictors), the network put in eval mode, the checkpoint written."""
        task = self.task
        train_loss, val_loss = self.metrics.get("train_loss"), self.metrics.get("val_loss")
        val_loss = None if val_loss is None else float(val_loss)
        sgd = task.optimization.fit_method == "sgd"
        check_fit(task, train_loss, val_loss, _loader(self.data.validation) if sgd else None)
        predictor = TrainedPredictor(task.network.eval(), task.spec, task.hparams.network, task.hparams.n_actuators,
                                     task.hparams["info"], self.ridge_path)
        if output.checkpoint_path is not None:
            with staged_file(output.checkpoint_path, output.overwrite) as partial:
                # Weights and hyperparameters only (no optimizer or loop state: an eofnn checkpoint is never
                # resumed), said explicitly: Lightning announces the choice it makes when none is given.
                self.trainer.save_checkpoint(partial, weights_only=True)
        return FitResult(predictor, train_loss, val_loss, rounds or [], output.checkpoint_path)


def solve(task: PredictorTask, data: FitData, optimization: OptimizationConfig, *, output: FitOutput | None = None,
          seed: int = 0, margin: Callable[[Any], Any] | None = None) -> Solved:
    """Fit ``task``'s network on ``data``, the one step of every fit that tells closed form from SGD.

    ``closed_form``: :func:`solve_closed_form` (``margin``: ``weights -> interval``, :func:`bind_margin`), then
    Lightning's ``validate`` on the validation batches (on the training ones when there are none but a checkpoint is
    to be written: validating attaches the trainer that saves). ``sgd``: Lightning's ``fit``, or with
    ``optimization.search`` the budgeted search (each trial seeded with ``seed``). ``closed_loop``: the closed-form
    fit, then :func:`~eofnn.training.through_loop.train_through_loop` on ``data.loop``. The fit's provenance
    (``task.hparams["info"]``) gets the alpha and its choice, the search, or the training through the loop.
    """
    output = output or FitOutput()
    info = task.hparams["info"]
    trainer = ridge_path = None
    try:
        with quiet_lightning():
            if optimization.fit_method == "closed_form":
                noise = noise_term(optimization, info.get("conditions"), task.spec.kind)
                solved = solve_closed_form(task.network, data.train, data.validation, optimization, margin, noise)
                info = info if noise is None else noise.recorded(info)
                metrics = {"train_loss": solved.train_loss, "condition": solved.condition, "alpha": solved.alpha}
                info["alpha"] = solved.alpha
                if solved.choice is not None:
                    info["alpha_choice"] = solved.choice.summary()
                    ridge_path = solved.choice.path
                task.hparams["info"] = info
                if data.validation is not None or output.checkpoint_path is not None:
                    trainer = make_trainer(optimization, output.progress)
                    checked = data.train if data.validation is None else data.validation
                    validated = trainer.validate(task, dataloaders=_loader(checked), verbose=False, weights_only=True)[0]
                    if data.validation is not None:
                        metrics.update(validated)
            elif optimization.fit_method == "closed_loop":
                start = solve_closed_form(task.network, data.train, data.validation, optimization)
                trainer, metrics = train_through_loop(task, data.loop, start, lambda callbacks: make_trainer(
                    optimization, output.progress, callbacks))
            elif optimization.search is not None:
                hp = task.hparams
                task, trainer, searched = run_search(
                    check_search(optimization.search, optimization.learning_rate), hp.network, optimization,
                    lambda net_cfg, opt: PredictorTask(net_cfg, hp.n_actuators, hp.spec, hp.grid,
                                                       resolve_normalize(net_cfg, asdict(opt)), info),
                    lambda t, tr: tr.fit(t, train_dataloaders=_loader(data.train),
                                         val_dataloaders=_loader(data.validation), weights_only=True),
                    lambda opt, callbacks: make_trainer(opt, output.progress, callbacks), seed, data.frames)
                info["search"] = searched
                task.hparams["info"] = info
                metrics = {"val_loss": searched["chosen"]["val_loss"], "lr": searched["chosen"]["lr"]}
            else:
                trainer = make_trainer(optimization, output.progress)
                trainer.fit(task, train_dataloaders=_loader(data.train), val_dataloaders=_loader(data.validation),
                            weights_only=True)
                metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    except SystemExit:
        # Lightning answers Ctrl-C inside fit/validate with its own shutdown and sys.exit(1): it is an interruption.
        raise KeyboardInterrupt from None
    return Solved(task, trainer, metrics, data, ridge_path)


#: Lightning's loggers of its rank-zero information lines ("GPU available: ...", "TPU available: ...", the LitLogger
#: tip, "`Trainer.fit` stopped: ..."): both, since Lightning's Fabric and PyTorch halves each name one.
LIGHTNING_INFO_LOGGERS = ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero")


@contextlib.contextmanager
def quiet_lightning() -> Iterator[None]:
    """While eofnn's own trainers are built and run: Lightning's banners and tips off, its real warnings kept.

    The information lines go through :data:`LIGHTNING_INFO_LOGGERS` (Lightning's documented way to quiet its
    console output is the level of its loggers; no Trainer option turns the accelerator banner or the tip off),
    held at WARNING here and restored afterwards, so a program that imports eofnn keeps its own logging set-up.
    Two of Lightning's warnings say nothing a user can act on and are ignored here, narrowly:

    - its suggestion of more DataLoader workers: eofnn's loaders hand over batches already simulated in memory;
    - ``isinstance(treespec, LeafSpec)`` is deprecated: Lightning's own ``CombinedLoader`` builds a torch
      ``LeafSpec`` (``lightning/pytorch/utilities/_pytree.py``, Lightning 2.6 with torch 2.13); eofnn never does.
    """
    loggers = [logging.getLogger(name) for name in LIGHTNING_INFO_LOGGERS]
    levels = [logger.level for logger in loggers]
    try:
        for logger in loggers:
            logger.setLevel(max(logger.getEffectiveLevel(), logging.WARNING))
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r"The '\w+_dataloader' does not have many workers")
            warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated",
                                    category=FutureWarning, module=r"lightning\.pytorch\.utilities\._pytree")
            yield
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)


def _loader(batches: Iterable | None) -> DataLoader | None:
    """Lightning's view of ``batches``: a DataLoader as it is, any other iterable of ready batches wrapped (no
    batching of its own)."""
    if batches is None or isinstance(batches, DataLoader):
        return batches
    return DataLoader(batches, batch_size=None)


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
