"""Closed-form ridge regression by streamed normal equations (float64, batched over groups)."""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from eofnn.errors import CollinearityWarning, require
from eofnn.training.alpha import AlphaChoice, MarginFunction, RidgePath, check_alpha_path
from eofnn.training.config import OptimizationConfig
from eofnn.training.noise import NoiseTerm, alpha_path
from eofnn.validation import NON_NEGATIVE, check_value


@dataclass
class RidgeSolution:
    """Result of :meth:`NormalEquations.solve`.

    Attributes
    ----------
    weights : Tensor
        ``(groups, features)`` solution.
    condition : float
        Largest condition number of ``D D^T`` over groups (before regularisation).
    """

    weights: torch.Tensor
    condition: float


class NormalEquations:
    """Accumulates ``D D^T`` and ``P D^T`` over streamed batches, then solves ``F = P D^T (D D^T + alpha I)^-1``.

    Data never has to fit in memory: each :meth:`update` adds one batch of ``(groups, samples, features)``
    regressors and ``(groups, samples)`` targets in float64.

    Each update is three batched products (``torch.baddbmm``) added into preallocated accumulators, with no
    per-batch temporaries. (Buffering small batches into a larger block was measured and is slower: the copy
    costs more than the products' start-up it saves.)
    """

    def __init__(self) -> None:
        self._gram: torch.Tensor | None = None
        self._cross: torch.Tensor | None = None  # (groups, features, 1)
        self._power: torch.Tensor | None = None  # (groups, 1, 1)
        self.n_samples = 0
        #: ``(groups,)``: the unit of a relative alpha when set (a noise power, :mod:`eofnn.training.noise`); unset,
        #: the mean diagonal of each group's Gram.
        self.ridge_unit: torch.Tensor | None = None

    def with_gram(self, gram: torch.Tensor, ridge_unit: torch.Tensor | None = None) -> NormalEquations:
        """These equations with another Gram matrix ``(groups, features, features)`` (the same cross products, target
        power and samples) and alpha's unit ``ridge_unit`` (:attr:`ridge_unit`)."""
        out = NormalEquations()
        out._gram, out._cross, out._power, out.n_samples = gram, self._cross, self._power, self.n_samples
        out.ridge_unit = ridge_unit
        return out

    @property
    def gram(self) -> torch.Tensor | None:
        """``(groups, features, features)``: ``D D^T`` accumulated so far."""
        return self._gram

    @property
    def cross(self) -> torch.Tensor | None:
        """``(groups, features)``: ``P D^T`` accumulated so far."""
        return None if self._cross is None else self._cross.squeeze(-1)

    @property
    def target_power(self) -> torch.Tensor | None:
        """``(groups,)``: the sum of squared targets accumulated so far."""
        return None if self._power is None else self._power.view(-1)

    @torch.no_grad()
    def update(self, features: torch.Tensor, target: torch.Tensor) -> None:
        x, t = features.to(torch.float64), target.to(torch.float64).unsqueeze(-1)
        groups, samples, n_features = x.shape
        if self._gram is None:
            self._gram = x.new_zeros(groups, n_features, n_features)
            self._cross = x.new_zeros(groups, n_features, 1)
            self._power = x.new_zeros(groups, 1, 1)
        xt = x.transpose(1, 2)
        torch.baddbmm(self._gram, xt, x, out=self._gram)
        torch.baddbmm(self._cross, xt, t, out=self._cross)
        torch.baddbmm(self._power, t.transpose(1, 2), t, out=self._power)
        self.n_samples += samples

    def solve(self, alpha: float = 0.0, relative: bool = True, warn_condition: float = 1e16) -> RidgeSolution:
        """Solve the regularised normal equations.

        Parameters
        ----------
        alpha : float
            Ridge parameter; if ``relative``, in units of the mean diagonal of ``D D^T`` (per group).
        relative : bool
            Whether ``alpha`` is relative.
        warn_condition : float
            Warn with :class:`CollinearityWarning` when ``cond(D D^T)`` exceeds this. The default flags
            regressors that are singular to float64 precision, such as closed-loop data recorded without excitation
            (the controller law ties ``y`` to past ``eps`` exactly); smooth turbulence alone reaches 1e12-1e15.
        """
        require(self._gram is not None, "no data accumulated: call update() before solve()")
        check_value("alpha", alpha, NON_NEGATIVE)
        n_features = self._gram.shape[-1]
        gram, scale = self.regular_gram(relative)
        absolute = alpha * scale
        eig = torch.linalg.eigvalsh(gram)
        condition = float((eig[:, -1] / eig[:, 0].clamp(min=torch.finfo(torch.float64).tiny)).max())
        if condition > warn_condition:
            warnings.warn(
                f"regressors are (near-)collinear: cond(D D^T) = {condition:.2e}; the fit is ill-posed "
                "(for closed-loop data, add dither excitation or raise alpha)", CollinearityWarning, stacklevel=3)
        regularised = gram + absolute.view(-1, 1, 1) * torch.eye(n_features, dtype=torch.float64, device=gram.device)
        chol, info = torch.linalg.cholesky_ex(regularised)
        if int(info.max()) == 0:
            weights = torch.cholesky_solve(self._cross, chol).squeeze(-1)
        else:  # singular without regularisation: least-norm solution
            weights = (torch.linalg.pinv(regularised, hermitian=True) @ self._cross).squeeze(-1)
        return RidgeSolution(weights, condition)

    def regular_gram(self, relative: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """``(D D^T, scale)``: the Gram matrix made regular where features are structurally zero, and the unit of a
        relative alpha per group (the mean of its diagonal, or :attr:`ridge_unit` when set; ones when ``relative`` is
        false)."""
        diagonal = self._gram.diagonal(dim1=1, dim2=2)
        # Features that are zero in every sample (neighbourhood slots beyond the pupil edge) get zero weight:
        # a unit on their diagonal makes the system regular without touching the other weights.
        structural = diagonal == 0
        gram = self._gram + torch.diag_embed(structural.to(torch.float64) * diagonal.mean(-1, keepdim=True))
        scale = diagonal.mean(-1) if relative else torch.ones_like(diagonal[:, 0])
        if relative and self.ridge_unit is not None:
            scale = self.ridge_unit
        return gram, scale

    def loss(self, weights: torch.Tensor) -> float:
        """Mean squared error of ``weights`` on the accumulated data, from the sufficient statistics."""
        w = weights.to(torch.float64)
        sse = self.target_power - 2 * (w * self.cross).sum(-1) + (w.unsqueeze(1) @ self._gram @ w.unsqueeze(-1)).view(-1)
        return float(sse.sum() / (self.n_samples * self._gram.shape[0]))


def supports_closed_form(network: nn.Module | type) -> bool:
    """Whether ``network`` exposes the linear-regression interface (``features``, ``group_targets``, ``load_solution``)."""
    return all(callable(getattr(network, name, None)) for name in ("features", "group_targets", "load_solution"))


@dataclass
class ClosedFormFit:
    """Outcome of :func:`fit_closed_form`: the training loss (nm²), the conditioning of the problem, the alpha
    used and, when it was chosen on validation data (``alpha: auto``), the choice with its validation curve."""

    train_loss: float
    condition: float
    alpha: float | None = None
    choice: AlphaChoice | None = None


def _accumulate(network: nn.Module, batches: Iterable[tuple[torch.Tensor, torch.Tensor]]) -> NormalEquations:
    equations = NormalEquations()
    for history, target in batches:
        equations.update(network.features(history), network.group_targets(target))
        del history, target  # freed before the next batch is built: one batch in memory at a time, not two
    return equations


@torch.no_grad()
def fit_closed_form(network: nn.Module, batches: Iterable[tuple[torch.Tensor, torch.Tensor]], alpha: float | str,
                    alpha_relative: bool = True, *, validation: Iterable[tuple[torch.Tensor, torch.Tensor]] | None = None,
                    alpha_path: Sequence[float] | None = None, interval: tuple[float, float] | None = None,
                    margin: MarginFunction | None = None, noise: NoiseTerm | None = None) -> ClosedFormFit:
    """Fit a linear network in one streamed pass: accumulate its normal equations over ``batches``, solve, load.

    The network's fitted state is overwritten. ``batches`` yields ``(history, target)`` pairs (a DataLoader of
    :class:`~eofnn.data.stream.SimulatedTelemetry`, or recorded telemetry cut into histories).

    ``alpha: "auto"`` chooses the ridge alpha on the ``validation`` batches (never the training ones) along
    ``alpha_path`` (:data:`~eofnn.training.alpha.DEFAULT_ALPHA_PATH` by default), from one eigendecomposition
    (:class:`~eofnn.training.alpha.RidgePath`); with ``interval`` the least-error alpha whose stable DM-gain
    interval (``margin(weights)``) contains it.

    ``noise`` (:class:`~eofnn.training.noise.NoiseTerm`) makes the training and validation normal equations those of
    histories carrying the noise the filter will meet (and alpha's unit a noise power when it asks); the training
    loss stays that of the data as recorded.
    """
    require(supports_closed_form(network),
            f"fit_method='closed_form' needs a linear network; {type(network).__name__} has no features()/"
            "load_solution(): use fit_method: sgd")
    recorded = _accumulate(network, batches)
    require(recorded.gram is not None, "no training data: the training stream yielded no batch")
    equations = recorded if noise is None else noise.adjust(recorded)
    if alpha == "auto":
        require(validation is not None, "alpha: auto needs validation data (data.val_frames > 0)")
        held = _accumulate(network, validation)
        if noise is not None and held.gram is not None:
            held = noise.adjust(held)
        path = RidgePath.compute(equations, held, check_alpha_path(alpha_path), alpha_relative)
        choice = path.select(interval, margin)
        weights = path.weights(choice.alpha)
        network.load_solution(weights.to(network.weight.dtype))
        return ClosedFormFit(recorded.loss(weights), path.condition, choice.alpha, choice)
    solution = equations.solve(alpha, alpha_relative)
    network.load_solution(solution.weights.to(network.weight.dtype))
    return ClosedFormFit(recorded.loss(solution.weights), solution.condition, float(alpha))


def solve_closed_form(network: nn.Module, train, validation, optimization: OptimizationConfig,
                      margin: MarginFunction | None = None, noise: NoiseTerm | None = None) -> ClosedFormFit:
    """The closed-form fit of ``optimization``: its fixed alpha, or (``alpha: auto``) the alpha chosen on
    ``validation`` under its ``select`` constraint (checked with ``margin``), modelling ``noise``
    (:mod:`eofnn.training.noise`)."""
    alpha = optimization.alpha_for(validation is not None)
    return fit_closed_form(network, train, alpha, optimization.alpha_relative,
                           validation=validation if alpha == "auto" else None, alpha_path=alpha_path(optimization, noise),
                           interval=optimization.dm_gain_interval, margin=margin, noise=noise)
