"""A small budgeted search for networks trained by gradient descent: the SGD twin of ``alpha: auto``.

``optimization.search: {lr: [1e-3, 3e-3, 1e-2], width: [16, 32, 64], patience: 2}`` trains one network per
combination (learning rate x hidden width, for networks with a ``hidden`` argument such as
:class:`~eofnn.models.mlp.MLP`) on the same training stream, each for at most ``optimization.epochs`` epochs with
early stopping on the validation loss (``patience`` epochs without improvement), keeps each trial's best epoch, and
returns the trial of least validation loss. The budget used (trials, epochs, frames seen) is reported beside the
result, so a network's number can be read against the linear filters' one closed-form pass.
"""

from __future__ import annotations

import copy
import inspect
import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import lightning as L

from eofnn.errors import ConfigError
from eofnn.models.build import import_class
from eofnn.training.config import SEARCH_KEYS, SearchSpace, check_search  # noqa: F401  (re-exported)


class KeepBest(L.Callback):
    """Keeps the network's state of its least validation loss and stops after ``patience`` epochs without a better
    one (early stopping that also restores the best epoch)."""

    def __init__(self, patience: int) -> None:
        self.patience, self.best, self.state, self.stale, self.epochs, self.best_epoch = patience, math.inf, None, 0, 0, 0

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        loss = trainer.callback_metrics.get("val_loss")
        self.epochs += 1
        value = math.inf if loss is None else float(loss)
        if value < self.best:
            self.best, self.best_epoch, self.stale = value, self.epochs, 0
            self.state = copy.deepcopy(pl_module.network.state_dict())
        else:
            self.stale += 1
            if self.stale >= self.patience:
                trainer.should_stop = True


def with_width(network: dict, width: int | None) -> dict:
    """``network`` with every hidden layer ``width`` wide (unchanged when ``width`` is ``None``)."""
    if width is None:
        return network
    init = dict(network.get("init_args") or {})
    layers = len(init.get("hidden", (64, 64)))
    return {**network, "init_args": {**init, "hidden": [width] * layers}}


def run_search(space: SearchSpace, network: dict, optimization, make_task: Callable[[dict, Any], L.LightningModule],
               fit: Callable[[L.LightningModule, L.Trainer], None], make_trainer: Callable[..., L.Trainer],
               seed: int, frames_per_epoch: int) -> tuple[L.LightningModule, L.Trainer, dict]:
    """Train one network per trial of ``space``; return the best task (at its best epoch), its trainer and a
    summary: the trials with their validation losses and epochs, the choice, and the budget used."""
    if space.width is not None:  # the class must take a width: checked before anything is trained
        cls = import_class(network["class_path"])
        if "hidden" not in inspect.signature(cls).parameters:
            raise ConfigError(f"optimization.search.width is for networks with a hidden argument (such as "
                              f"eofnn.models.mlp.MLP); {network['class_path']} has none")
    trials, best = [], None
    for lr, width in space.trials:
        L.seed_everything(seed, workers=True, verbose=False)
        trial_opt = replace(optimization, lr=lr, search=None)
        task = make_task(with_width(network, width), trial_opt)
        keep = KeepBest(space.patience)
        trainer = make_trainer(trial_opt, callbacks=[keep])
        fit(task, trainer)
        if keep.state is not None:
            task.network.load_state_dict(keep.state)
        trials.append({"lr": lr, "width": width, "val_loss": keep.best if math.isfinite(keep.best) else None,
                       "epochs": keep.epochs, "best_epoch": keep.best_epoch})
        if math.isfinite(keep.best) and (best is None or keep.best < best[0]):
            best = (keep.best, task, trainer, len(trials) - 1)
    if best is None:
        raise ConfigError(f"every trial of optimization.search gave a non-finite validation loss "
                          f"({len(trials)} trials): lower the learning rates")
    epochs = sum(t["epochs"] for t in trials)
    summary = {"trials": trials, "chosen": trials[best[3]], "budget": {
        "trials": len(trials), "epochs": epochs, "frames": epochs * frames_per_epoch,
        "max_epochs_per_trial": optimization.epochs, "patience": space.patience}}
    return best[1], best[2], summary
