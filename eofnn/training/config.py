"""How a predictor is fitted (:class:`OptimizationConfig`) and the checks of its search, free of torch and Lightning.

The command line builds its parsers from this config and checks its values before the fitting code
(:mod:`eofnn.training.task`, :mod:`eofnn.training.search`, which re-export these names) is imported: seconds of
imports that ``--help`` and a config error do without.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import ClassVar

from eofnn.errors import ConfigError
from eofnn.training.alpha import check_alpha_path, check_select
from eofnn.validation import NON_NEGATIVE, Constraint, Either, Interval, IsBool, OneOf, OrNone, validated

SEARCH_KEYS = ("lr", "width", "patience")


@dataclass(frozen=True)
class SearchSpace:
    """Learning rates, hidden widths (``None``: the network's own) and early-stopping patience (epochs)."""

    lr: tuple[float, ...]
    width: tuple[int, ...] | None
    patience: int

    @property
    def trials(self) -> list[tuple[float, int | None]]:
        return list(itertools.product(self.lr, self.width or (None,)))


def check_search(search: dict | None, lr: float, where: str = "optimization.") -> SearchSpace | None:
    """The search ``search`` describes (``lr`` defaults to the config's own), or one line naming what is wrong."""
    if search is None:
        return None
    if not isinstance(search, dict) or not set(search) <= set(SEARCH_KEYS) or not search:
        raise ConfigError(f"{where}search={search!r} is invalid: give some of {', '.join(SEARCH_KEYS)}, e.g. "
                          "{lr: [1.0e-3, 3.0e-3], width: [16, 32], patience: 2}")
    lrs = search.get("lr", [lr])
    if not (isinstance(lrs, list) and lrs and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                   and math.isfinite(v) and v > 0 for v in lrs)):
        raise ConfigError(f"{where}search.lr={lrs!r} is invalid: it must be a non-empty list of learning rates > 0")
    widths = search.get("width")
    if widths is not None and not (isinstance(widths, list) and widths and all(
            isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 65536 for v in widths)):
        raise ConfigError(f"{where}search.width={widths!r} is invalid: it must be a non-empty list of integers in "
                          "[1, 65536] (hidden units per layer)")
    patience = search.get("patience", 2)
    if not (isinstance(patience, int) and not isinstance(patience, bool) and 1 <= patience <= 1000):
        raise ConfigError(f"{where}search.patience={patience!r} is invalid: it must be an integer in [1, 1000] (epochs)")
    space = SearchSpace(tuple(float(v) for v in lrs), None if widths is None else tuple(widths), patience)
    if len(space.trials) > 64:
        raise ConfigError(f"{where}search has {len(space.trials)} trials: at most 64 (each trains a network)")
    return space


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
    normalize : bool or None
        Gradient descent on scaled numbers: the history divided by its RMS and the output multiplied by the
        targets' RMS (both measured on the first training batch and saved; :class:`~eofnn.models.normalized.Normalized`).
        Unset: on for networks that are not eofnn's own (those scale themselves or are fitted in closed form).
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
    normalize: bool | None = None

    _constraints: ClassVar[dict[str, Constraint]] = {
        "fit_method": OneOf(FIT_METHODS),
        "alpha": OrNone(Either(Interval(0, 1e12), OneOf(("auto",)))),
        "alpha_relative": IsBool(),
        "optimizer": OneOf(OPTIMIZERS),
        "lr": Interval(0, 1e3, closed="right"),
        "weight_decay": NON_NEGATIVE,
        "epochs": Interval(1, 100_000, integer=True),
        "accelerator": OneOf(ACCELERATORS),
        "normalize": OrNone(IsBool()),
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


__all__ = ["ACCELERATORS", "FALLBACK_ALPHA", "FIT_METHODS", "OPTIMIZERS", "SEARCH_KEYS", "OptimizationConfig",
           "SearchSpace", "check_search"]
