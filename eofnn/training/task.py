"""One LightningModule trains every predictor by gradient descent; linear ones may be fitted in closed form first.

The task builds its own network from its saved hyperparameters (torchgeo's pattern), so a checkpoint reloads
with ``PredictorTask.load_from_checkpoint(path, weights_only=True)`` and nothing else; it never knows which
network it trains.
"""

from __future__ import annotations

import math
import warnings

import lightning as L
import torch

from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.models.build import OWN_NETWORKS, build_network, input_dtype, resolve_class_path
from eofnn.models.normalized import Normalized
from eofnn.training.config import (  # noqa: F401  (re-exported: the config's home before it moved)
    ACCELERATORS,
    FALLBACK_ALPHA,
    FIT_METHODS,
    OPTIMIZERS,
    OptimizationConfig,
)
from eofnn.training.rollout import LoopBatch, log_loop_residual, loop_step


class PredictorTask(L.LightningModule):
    """Trains the network described by ``network`` to map history tensors to the cancelling command.

    Parameters
    ----------
    network : dict
        ``{"class_path": ..., "init_args": {...}}`` of the network (see :func:`eofnn.models.build.build_network`).
    n_actuators : int
        Active actuators ``K``.
    spec : dict
        The :class:`~eofnn.data.history.HistorySpec` fields (kind, history length, delay).
    grid : dict
        The :class:`~eofnn.sim.grid.ActuatorGrid` fields, for networks that need neighbourhoods.
    optimization : dict
        The :class:`OptimizationConfig` fields.
    info : dict, optional
        Provenance recorded in the checkpoint (scenario, data settings).
    """

    def __init__(self, network: dict, n_actuators: int, spec: dict, grid: dict, optimization: dict | None = None,
                 info: dict | None = None) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.spec = HistorySpec(**spec)
        self.optimization = OptimizationConfig(**(optimization or {}))
        # Training through the loop takes its own optimiser steps (each backpropagates window by window).
        self.automatic_optimization = self.optimization.fit_method != "closed_loop"
        self.configure_models()

    def configure_models(self) -> None:
        """Build the network from the hyperparameters (also what ``load_from_checkpoint`` runs)."""
        hp = self.hparams
        network = build_network(hp.network, hp.n_actuators, self.spec.n_taps, hp.grid, self.spec.kind,
                                self.spec.delay_frames)
        # Unset here (older checkpoints, direct use): unscaled; the fits resolve it first (resolve_normalize).
        self.network = Normalized(network) if (hp.optimization or {}).get("normalize") else network

    @property
    def network_name(self) -> str:
        return str(self.hparams.network.get("class_path"))

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        """The network's commands (nm) for histories (nm), given in the network's own dtype.

        Histories are float64 and unscaled (nm of optical path): a float32 network gets them converted; a network
        that wants inputs of order one scales them itself (as :class:`~eofnn.models.mlp.MLP` does) or is trained
        through :class:`~eofnn.models.normalized.Normalized` (``optimization.normalize``).
        """
        try:
            return self.network(history.to(input_dtype(self.network)))
        except Exception as err:  # a user's forward: one line naming it, not Lightning's traceback
            text = str(err).strip().splitlines()
            raise ConfigError(f"network {self.network_name}: forward raised {type(err).__name__}"
                              f"{': ' + text[0] if text else ''}") from None

    def _loss(self, batch) -> torch.Tensor:
        history, target = batch
        prediction = self(history)
        if prediction.shape != target.shape:
            raise ConfigError(f"network {self.network_name} returned shape {tuple(prediction.shape)} for a history "
                              f"of shape {tuple(history.shape)}: it must return {tuple(target.shape)}")
        return (prediction - target.to(prediction.dtype)).pow(2).mean()

    def training_step(self, batch, batch_idx):
        if isinstance(batch, LoopBatch):
            return loop_step(self, batch)
        if isinstance(self.network, Normalized) and not self.network.fitted:
            self.network.fit_scales(*batch)
        loss = self._loss(batch)
        self.log("train_loss", loss, prog_bar=True, on_step=False, on_epoch=True, batch_size=batch[0].shape[0])
        if isinstance(self.network, Normalized):  # descend on the scaled error; the logged loss stays in nm^2
            return loss / self.network.target_scale_nm.to(loss.dtype) ** 2
        return loss

    def validation_step(self, batch, batch_idx):
        if isinstance(batch, LoopBatch):
            return log_loop_residual(self, batch, "val_loss")
        loss = self._loss(batch)
        self.log("val_loss", loss, prog_bar=True, batch_size=batch[0].shape[0])
        return loss

    def configure_optimizers(self):
        opt = self.optimization
        if not any(p.requires_grad for p in self.network.parameters()):
            raise ConfigError(f"network {self.network_name} has no trainable parameters: there is nothing for "
                              "optimization.fit_method sgd to fit")
        params, name, lr = self.network.parameters(), opt.gradient_optimizer, opt.learning_rate
        if name == "lbfgs":
            return torch.optim.LBFGS(params, lr=lr, history_size=50, max_iter=20, line_search_fn="strong_wolfe")
        if name == "sgd":
            return torch.optim.SGD(params, lr=lr, momentum=0.9, weight_decay=opt.weight_decay)
        return torch.optim.Adam(params, lr=lr, weight_decay=opt.weight_decay)


def resolve_normalize(network: dict, optimization: dict | None) -> dict:
    """``optimization`` with ``normalize`` decided: unset, on for a network trained by gradient descent that is not
    eofnn's own (a closed-form fit solves the unscaled problem exactly)."""
    optimization = dict(optimization or {})
    if optimization.get("normalize") is None:
        try:
            own = resolve_class_path(network.get("class_path")) in OWN_NETWORKS
        except (ConfigError, AttributeError):
            own = True  # build_network says what is wrong with it
        optimization["normalize"] = optimization.get("fit_method", "closed_form") == "sgd" and not own
    return optimization


@torch.no_grad()
def trivial_losses(batches, kind: str) -> dict[str, float]:
    """Mean squared error (nm^2) of the trivial predictors on ``(history, target)`` batches.

    ``zero command`` (no correction) and, for an open-loop history, the ``pseudo-integrator``: the latest
    pseudo-open-loop value (tap 0), with its least-squares scale (which absorbs the sign and the DM gain).
    """
    n, tt, th, hh = 0, 0.0, 0.0, 0.0
    for history, target in batches:
        t = target.to(torch.float64)
        n += t.numel()
        tt += float(t.pow(2).sum())
        if kind == "open_loop":
            h = history[..., 0].to(torch.float64)
            th += float((t * h).sum())
            hh += float(h.pow(2).sum())
    if n == 0:
        return {}
    losses = {"zero command": tt / n}
    if kind == "open_loop" and hh > 0:
        losses["pseudo-integrator"] = max(tt - th * th / hh, 0.0) / n
    return losses


def check_fit(task: PredictorTask, train_loss: float | None, val_loss: float | None, val_batches=None) -> None:
    """After a fit and before anything is saved: refuse non-finite losses, warn when gradient descent did not beat
    the trivial predictors on the validation data (``val_batches``: compared only when given)."""
    name = task.network_name
    for label, loss in (("training", train_loss), ("validation", val_loss)):
        if loss is not None and not math.isfinite(loss):
            raise ConfigError(f"network {name} gave a {label} loss of {loss} (not finite): nothing was saved; "
                              "lower optimization.lr or look for NaN/inf in its forward")
    if val_loss is None or val_batches is None:
        return
    trivial = trivial_losses(val_batches, task.spec.kind)
    if trivial and val_loss >= min(trivial.values()):
        others = ", ".join(f"{k} {v:.4g}" for k, v in trivial.items())
        own = resolve_class_path(name) in OWN_NETWORKS if name != "None" else True
        hint = "" if own or task.hparams.optimization.get("normalize") else "optimization.normalize: true, "
        warnings.warn(f"network {name} does not beat the trivial predictors on validation data (loss {val_loss:.4g} "
                      f"nm^2; {others} nm^2): it learnt nothing useful; try {hint}more epochs or another lr",
                      stacklevel=2)
