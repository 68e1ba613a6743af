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


FIT_METHODS = ("closed_form", "sgd", "closed_loop")
#: The relative ridge alpha of a closed-form fit with no validation data to choose one on (``alpha`` unset).
FALLBACK_ALPHA = 1e-9
OPTIMIZERS = ("adam", "sgd", "lbfgs")
#: The optimiser and learning rate of each fit method when ``optimizer`` and ``lr`` are unset.
DEFAULT_OPTIMIZER = {"closed_form": "adam", "sgd": "adam", "closed_loop": "lbfgs"}
DEFAULT_LR = {"adam": 1e-3, "sgd": 1e-3, "lbfgs": 1.0}
ACCELERATORS = ("auto", "cpu", "cuda", "gpu", "mps")
#: How a closed-form fit accounts for white WFS noise on its pseudo-open-loop histories (:mod:`eofnn.training.noise`).
NOISE_MODELS = ("none", "errors_in_variables", "per_mode_snr")


@dataclass
@validated
class OptimizationConfig:
    """How a predictor is fitted.

    Parameters
    ----------
    fit_method : {"closed_form", "sgd", "closed_loop"}
        ``closed_form``: one streamed pass of ridge regression (linear networks); ``sgd``: gradient descent;
        ``closed_loop``: a linear network trained through the closed loop (:mod:`eofnn.training.through_loop`):
        started from the closed-form fit, it descends on the mean squared closed-loop residual of the same training
        frames (the same turbulence and noise draws, the same ``data.plant_range``), backpropagated through windows
        of the loop; the epoch of least residual on the validation frames is kept (the closed-form start included).
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
    optimizer : {"adam", "sgd", "lbfgs"}, optional
        Gradient optimiser (``fit_method: sgd`` or ``closed_loop``); unset, ``adam`` for ``sgd`` and ``lbfgs`` for
        ``closed_loop`` (one quasi-Newton step on all the training windows per epoch).
    lr : float, optional
        Learning rate; unset, 1e-3 for ``adam`` and ``sgd``, 1 for ``lbfgs``.
    weight_decay : float
        Weight decay of the gradient optimiser.
    epochs : int
        Epochs of gradient descent (a closed-form fit is one pass).
    loop_window : int
        ``closed_loop``: frames of each window whose residuals are the loss and backpropagated through.
    loop_warmup : int
        ``closed_loop``: frames before each window, run without gradients from a reset of the loop (truncated
        backpropagation: the loop's state comes from them, its gradient does not).
    accelerator : str
        Lightning accelerator: ``auto`` (CUDA when present), ``cpu``, ``cuda``, ``gpu`` or ``mps``.
    normalize : bool or None
        Gradient descent on scaled numbers: the history divided by its RMS and the output multiplied by the
        targets' RMS (both measured on the first training batch and saved; :class:`~eofnn.models.normalized.Normalized`).
        Unset: on for networks that are not eofnn's own (those scale themselves or are fitted in closed form).
    noise_model : {"none", "errors_in_variables", "per_mode_snr"}
        How a closed-form fit on pseudo-open-loop histories accounts for the white WFS noise of its training data
        (the level identified from the telemetry, or the scenario's; :mod:`eofnn.training.noise`). ``none``: the
        data as recorded (already the minimum-error predictor for histories as noisy as the training data's).
        ``errors_in_variables``: the noise covariance subtracted from the normal equations, a filter for noise-free
        histories. ``per_mode_snr``: the ridge alpha in units of the noise power (samples x sigma²) instead of
        each group's signal power, so every mode (with ``network.init_args.structure: modal``) or actuator is shrunk
        by its own signal-to-noise ratio; unset, ``alpha_path`` is then 1e-4 to 1e2 (two per decade).
    noise_at_deployment_nm : float, optional
        The white WFS noise (nm RMS per actuator and frame) the filter will meet: the normal equations are made
        those of histories with that noise (``+ n (sigma_deploy² - sigma_train²) I``, the Wiener filter for it),
        validation included. Unset: the training data's noise.
    """

    fit_method: str = "closed_form"
    alpha: float | str | None = None
    alpha_relative: bool = True
    alpha_path: list[float] | None = None
    select: dict | None = None
    search: dict | None = None
    optimizer: str | None = None
    lr: float | None = None
    weight_decay: float = 0.0
    epochs: int = 1
    loop_window: int = 100
    loop_warmup: int = 50
    accelerator: str = "auto"
    normalize: bool | None = None
    noise_model: str = "none"
    noise_at_deployment_nm: float | None = None

    _constraints: ClassVar[dict[str, Constraint]] = {
        "fit_method": OneOf(FIT_METHODS),
        "alpha": OrNone(Either(Interval(0, 1e12), OneOf(("auto",)))),
        "alpha_relative": IsBool(),
        "optimizer": OrNone(OneOf(OPTIMIZERS)),
        "lr": OrNone(Interval(0, 1e3, closed="right")),
        "weight_decay": NON_NEGATIVE,
        "epochs": Interval(1, 100_000, integer=True),
        "loop_window": Interval(1, 100_000, integer=True, unit="frames"),
        "loop_warmup": Interval(0, 100_000, integer=True, unit="frames"),
        "accelerator": OneOf(ACCELERATORS),
        "normalize": OrNone(IsBool()),
        "noise_model": OneOf(NOISE_MODELS),
        "noise_at_deployment_nm": OrNone(Interval(0, 1e6, unit="nm")),
    }
    _where: ClassVar[str] = "optimization."

    def __post_init__(self) -> None:
        if self.fit_method == "sgd" and self.alpha == "auto":
            raise ConfigError("optimization.alpha='auto' is invalid with fit_method: sgd: the ridge alpha belongs to "
                              "the closed-form fit (give fit_method: closed_form, or leave alpha unset)")
        if self.fit_method == "sgd" and self.select is not None:
            raise ConfigError("optimization.select is invalid with fit_method: sgd: it constrains the closed-form "
                              "fit's alpha: auto")
        if self.fit_method == "closed_loop" and self.select is not None:
            raise ConfigError("optimization.select is invalid with fit_method: closed_loop: it constrains the "
                              "closed-form alpha that training through the loop then moves away from")
        if self.search is not None and self.fit_method != "sgd":
            raise ConfigError("optimization.search is for fit_method: sgd (a closed-form fit tunes alpha: auto)")
        if self.noise_aware and self.fit_method != "closed_form":
            raise ConfigError(f"optimization.noise_model={self.noise_model!r} / noise_at_deployment_nm="
                              f"{self.noise_at_deployment_nm!r} act on the normal equations of fit_method: closed_form, "
                              f"not {self.fit_method!r}")
        if self.noise_model == "errors_in_variables" and self.noise_at_deployment_nm is not None:
            raise ConfigError("optimization.noise_model: errors_in_variables fits for noise-free histories: it is "
                              "noise_at_deployment_nm: 0; give one of the two")
        if self.noise_model == "per_mode_snr" and not self.alpha_relative:
            raise ConfigError("optimization.noise_model: per_mode_snr measures alpha in units of the noise power: "
                              "alpha_relative: false contradicts it")
        check_search(self.search, self.learning_rate)
        check_alpha_path(self.alpha_path)
        check_select(self.select)
        if self.select is not None and self.ridge_alpha != "auto":
            raise ConfigError(f"optimization.select needs alpha: auto, not alpha={self.alpha!r}: the constraint "
                              "chooses among the alphas of the path")

    @property
    def noise_aware(self) -> bool:
        """Whether the fit models the WFS noise (``noise_model`` or ``noise_at_deployment_nm`` set)."""
        return self.noise_model != "none" or self.noise_at_deployment_nm is not None

    @property
    def gradient_optimizer(self) -> str:
        """The optimiser of a fit by gradient descent: ``optimizer``, or unset the fit method's default."""
        return self.optimizer or DEFAULT_OPTIMIZER[self.fit_method]

    @property
    def learning_rate(self) -> float:
        """``lr``, or unset the default of :attr:`gradient_optimizer`."""
        return DEFAULT_LR[self.gradient_optimizer] if self.lr is None else self.lr

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


__all__ = ["ACCELERATORS", "DEFAULT_LR", "DEFAULT_OPTIMIZER", "FALLBACK_ALPHA", "FIT_METHODS", "NOISE_MODELS", "OPTIMIZERS",
           "SEARCH_KEYS", "OptimizationConfig", "SearchSpace", "check_search"]
