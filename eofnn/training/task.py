"""One LightningModule trains every predictor by gradient descent; linear ones may be fitted in closed form first.

The task builds its own network from its saved hyperparameters (torchgeo's pattern), so a checkpoint reloads
with ``PredictorTask.load_from_checkpoint(path, weights_only=True)`` and nothing else; it never knows which
network it trains.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import lightning as L
import torch

from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.models.build import build_network, input_dtype
from eofnn.training.alpha import check_alpha_path, check_select
from eofnn.training.search import check_search
from eofnn.validation import NON_NEGATIVE, Constraint, Either, Interval, IsBool, OneOf, OrNone, validated

FIT_METHODS = ("closed_form", "sgd")
#: The relative ridge alpha of a closed-form fit with no validation data to choose one on (``alpha`` unset).
FALLBACK_ALPHA = 1e-9
OPTIMIZERS = ("adam", "sgd", "lbfgs")
ACCELERATORS = ("auto", "cpu", "cuda", "gpu", "mps")


@dataclass
@validated
class OptimizationConfig:
    """How a predictor is fitted.

    Parameters
    ----------
    fit_method : {"closed_form", "sgd"}
        ``closed_form``: one streamed pass of ridge regression (linear networks); ``sgd``: gradient descent.
    alpha : float or "auto", optional
        Ridge parameter of the closed-form fit. ``auto`` (and unset, for a closed-form fit) chooses it on the
        validation frames along ``alpha_path`` (:mod:`eofnn.training.alpha`): the least validation error, or under
        ``select`` the least-error alpha that meets the robustness constraint. A number means that number.
    alpha_relative : bool
        ``alpha`` in units of the mean diagonal of ``D D^T`` (per group) rather than absolute.
    alpha_path : list of float, optional
        Alphas searched by ``alpha: auto``, strictly increasing; unset, 1e-14 to 1e-2 with two per decade.
    search : dict, optional
        A budgeted search for ``fit_method: sgd`` (:mod:`eofnn.training.search`): ``{lr: [...], width: [...],
        patience: 2}`` trains one network per learning rate x hidden width, each with early stopping on the
        validation loss, and keeps the best; the budget used goes beside the result.
    select : dict, optional
        A robustness constraint on the ``auto`` choice: ``{dm_gain_interval: [low, high]}`` keeps the best alpha
        whose analytic stable DM-gain interval contains ``[low, high]`` (which must contain 1).
    optimizer : {"adam", "sgd", "lbfgs"}
        Gradient optimiser (``fit_method: sgd``).
    lr : float
        Learning rate.
    weight_decay : float
        Weight decay of the gradient optimiser.
    epochs : int
        Epochs of gradient descent (a closed-form fit is one pass).
    accelerator : str
        Lightning accelerator: ``auto`` (CUDA when present), ``cpu``, ``cuda``, ``gpu`` or ``mps``.
    """

    fit_method: str = "closed_form"
    alpha: float | str | None = None
    alpha_relative: bool = True
    alpha_path: list[float] | None = None
    select: dict | None = None
    search: dict | None = None
    optimizer: str = "adam"
    lr: float = 1e-3
    weight_decay: float = 0.0
    epochs: int = 1
    accelerator: str = "auto"

    _constraints: ClassVar[dict[str, Constraint]] = {
        "fit_method": OneOf(FIT_METHODS),
        "alpha": OrNone(Either(Interval(0, 1e12), OneOf(("auto",)))),
        "alpha_relative": IsBool(),
        "optimizer": OneOf(OPTIMIZERS),
        "lr": Interval(0, 1e3, closed="right"),
        "weight_decay": NON_NEGATIVE,
        "epochs": Interval(1, 100_000, integer=True),
        "accelerator": OneOf(ACCELERATORS),
    }
    _where: ClassVar[str] = "optimization."

    def __post_init__(self) -> None:
        if self.fit_method == "sgd" and self.alpha == "auto":
            raise ConfigError("optimization.alpha='auto' is invalid with fit_method: sgd: the ridge alpha belongs to "
                              "the closed-form fit (give fit_method: closed_form, or leave alpha unset)")
        if self.fit_method == "sgd" and self.select is not None:
            raise ConfigError("optimization.select is invalid with fit_method: sgd: it constrains the closed-form "
                              "fit's alpha: auto")
        if self.search is not None and self.fit_method != "sgd":
            raise ConfigError("optimization.search is for fit_method: sgd (a closed-form fit tunes alpha: auto)")
        check_search(self.search, self.lr)
        check_alpha_path(self.alpha_path)
        check_select(self.select)
        if self.select is not None and self.ridge_alpha != "auto":
            raise ConfigError(f"optimization.select needs alpha: auto, not alpha={self.alpha!r}: the constraint "
                              "chooses among the alphas of the path")

    @property
    def ridge_alpha(self) -> float | str:
        """The alpha of a closed-form fit: the number given, or ``"auto"`` (also when unset)."""
        return "auto" if self.alpha is None else self.alpha

    def alpha_for(self, has_validation: bool) -> float | str:
        """The alpha of a fit with or without validation data: unset, ``auto`` when there is validation data to
        choose it on and :data:`FALLBACK_ALPHA` otherwise (an explicit ``auto`` needs validation data)."""
        if self.alpha is None and not has_validation:
            return FALLBACK_ALPHA
        return self.ridge_alpha

    @property
    def dm_gain_interval(self) -> tuple[float, float] | None:
        """The DM-gain interval ``select`` asks the chosen alpha to keep stable (``None``: no constraint)."""
        return check_select(self.select)


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
        self.configure_models()

    def configure_models(self) -> None:
        """Build the network from the hyperparameters (also what ``load_from_checkpoint`` runs)."""
        hp = self.hparams
        self.network = build_network(hp.network, hp.n_actuators, self.spec.n_taps, hp.grid, self.spec.kind,
                                     self.spec.delay_frames)

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        """The network's commands (nm) for histories (nm), given in the network's own dtype.

        Histories are float64 and unscaled (nm of optical path): a float32 network gets them converted, and a
        network that wants inputs of order one scales them itself (as :class:`~eofnn.models.mlp.MLP` does).
        """
        return self.network(history.to(input_dtype(self.network)))

    def _loss(self, batch) -> torch.Tensor:
        history, target = batch
        prediction = self(history)
        return (prediction - target.to(prediction.dtype)).pow(2).mean()

    def training_step(self, batch, batch_idx):
        loss = self._loss(batch)
        self.log("train_loss", loss, prog_bar=True, on_step=False, on_epoch=True, batch_size=batch[0].shape[0])
        return loss

    def validation_step(self, batch, batch_idx):
        loss = self._loss(batch)
        self.log("val_loss", loss, prog_bar=True, batch_size=batch[0].shape[0])
        return loss

    def configure_optimizers(self):
        opt = self.optimization
        params = self.network.parameters()
        if opt.optimizer == "lbfgs":
            return torch.optim.LBFGS(params, lr=opt.lr, history_size=50, max_iter=20, line_search_fn="strong_wolfe")
        if opt.optimizer == "sgd":
            return torch.optim.SGD(params, lr=opt.lr, momentum=0.9, weight_decay=opt.weight_decay)
        return torch.optim.Adam(params, lr=opt.lr, weight_decay=opt.weight_decay)

