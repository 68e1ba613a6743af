"""One LightningModule trains every predictor: closed form for linear ones, or SGD for any ``nn.Module``."""

from __future__ import annotations

import lightning as L
import torch
from torch import nn

from eofnn.errors import require
from eofnn.training.ridge import NormalEquations

FIT_METHODS = ("closed_form", "sgd")
OPTIMIZERS = ("adam", "sgd", "lbfgs")


def supports_closed_form(network: nn.Module | type) -> bool:
    """Whether ``network`` exposes the linear-regression interface (``features``, ``group_targets``, ``load_solution``)."""
    return all(callable(getattr(network, name, None)) for name in ("features", "group_targets", "load_solution"))


class PredictorTask(L.LightningModule):
    """Trains ``network`` to map history tensors to the cancelling command.

    The task never knows which predictor it trains: networks that expose the linear-regression interface can be
    fitted in closed form (normal equations accumulated over the streamed epoch, solved once), every network by
    gradient descent on the mean squared error.

    Parameters
    ----------
    network : nn.Module
        Maps ``(batch, K, taps)`` to ``(batch, K)``.
    fit_method : {"closed_form", "sgd"}
        How to fit.
    alpha : float
        Ridge parameter of the closed-form fit.
    alpha_relative : bool
        ``alpha`` in units of the mean diagonal of ``D D^T`` (per group) rather than absolute.
    optimizer : {"adam", "sgd", "lbfgs"}
        Gradient optimiser for ``sgd``.
    lr : float
        Learning rate.
    weight_decay : float
        Weight decay of the gradient optimiser.
    spec, network_config, grid : dict
        Recorded in the checkpoint so that :func:`eofnn.training.checkpoint.load_predictor` can rebuild the predictor.
    """

    def __init__(self, network: nn.Module, fit_method: str = "closed_form", alpha: float = 1e-9,
                 alpha_relative: bool = True, optimizer: str = "adam", lr: float = 1e-3, weight_decay: float = 0.0,
                 spec: dict | None = None, network_config: dict | None = None, grid: dict | None = None,
                 info: dict | None = None) -> None:
        super().__init__()
        require(fit_method in FIT_METHODS, f"fit_method={fit_method!r} is invalid: allowed are {', '.join(FIT_METHODS)}")
        require(optimizer in OPTIMIZERS, f"optimizer={optimizer!r} is invalid: allowed are {', '.join(OPTIMIZERS)}")
        if fit_method == "closed_form":
            require(supports_closed_form(network),
                    f"fit_method='closed_form' needs a linear network; {type(network).__name__} has no features()/"
                    "load_solution(): use fit_method='sgd'")
        self.save_hyperparameters(ignore=["network"])
        self.network = network
        self.automatic_optimization = fit_method == "sgd"
        self.normal_equations: NormalEquations | None = None
        self.last_solution = None

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        return self.network(history)

    def _loss(self, batch) -> torch.Tensor:
        history, target = batch
        prediction = self.network(history)
        return (prediction - target.to(prediction.dtype)).pow(2).mean()

    def training_step(self, batch, batch_idx):
        if self.hparams.fit_method == "closed_form":
            history, target = batch
            if self.normal_equations is None:
                self.normal_equations = NormalEquations()
            self.normal_equations.update(self.network.features(history), self.network.group_targets(target))
            return None
        loss = self._loss(batch)
        self.log("train_loss", loss, prog_bar=True, on_step=False, on_epoch=True, batch_size=batch[0].shape[0])
        return loss

    def solve(self) -> None:
        """Solve the accumulated normal equations into the network (fitted state is overwritten)."""
        if self.normal_equations is None:
            return
        solution = self.normal_equations.solve(self.hparams.alpha, self.hparams.alpha_relative)
        self.network.load_solution(solution.weights.to(self.network.weight.dtype))
        self.train_loss_closed_form = self.normal_equations.loss(solution.weights)
        self.last_solution = solution
        self.normal_equations = None
        if self._trainer is not None:
            self.log("train_loss", self.train_loss_closed_form)
            self.log("condition", solution.condition)

    # Validation runs before on_train_epoch_end, so the solve happens when validation starts (or at epoch end).
    def on_validation_epoch_start(self) -> None:
        self.solve()

    def on_train_epoch_end(self) -> None:
        self.solve()

    def validation_step(self, batch, batch_idx):
        loss = self._loss(batch)
        self.log("val_loss", loss, prog_bar=True, batch_size=batch[0].shape[0])
        return loss

    def configure_optimizers(self):
        if self.hparams.fit_method == "closed_form":
            return None
        params = self.network.parameters()
        if self.hparams.optimizer == "lbfgs":
            return torch.optim.LBFGS(params, lr=self.hparams.lr, history_size=50, max_iter=20,
                                     line_search_fn="strong_wolfe")
        if self.hparams.optimizer == "sgd":
            return torch.optim.SGD(params, lr=self.hparams.lr, momentum=0.9, weight_decay=self.hparams.weight_decay)
        return torch.optim.Adam(params, lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
