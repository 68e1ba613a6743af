"""Choosing the ridge alpha on validation data: the whole regularisation path at about the cost of one solve.

One eigendecomposition of each group's training Gram matrix, ``D D^T = V diag(l) V^T``, gives the ridge solution
for every alpha, ``W(alpha) = V diag(1 / (l + alpha s)) V^T (P D^T)`` (``s``: the unit of a relative alpha), and
the validation error of every alpha from the validation stream's sufficient statistics alone
(``|P_v|^2 - 2 W . (P_v D_v^T) + W (D_v D_v^T) W^T``), rotated once into the eigenbasis: no second pass over the
data, no refit per alpha. The chosen alpha is the one of least validation error, or, under a robustness
constraint, the least-error one whose analytic stable DM-gain interval contains the one asked for.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from eofnn.errors import ConfigError, require
from eofnn.lazy import lazy_module

torch = lazy_module("torch")

#: The default path of relative alphas: 1e-14 to 1e-2, two values per decade.
DEFAULT_ALPHA_PATH = tuple(float(f"{10 ** (e / 2):.3g}") for e in range(-28, -3))

#: An alpha at its path's lower end and the unregularised fit agree when their validation errors differ by less than
#: this (relative): a smaller alpha would then barely matter.
NEGLIGIBLE_CHANGE = 1e-3


def unregularised_change(choice: dict) -> float | None:
    """``unregularised validation error / chosen one - 1`` of a choice's summary (:meth:`AlphaChoice.summary`) made at
    its path's lower end (above 0); ``None`` for any other choice, or when either error is unknown."""
    path, zero = choice["path"]["alpha"], choice.get("unregularised_val_loss")
    if choice["alpha"] != path[0] or path[0] == 0 or zero is None or not choice.get("val_loss"):
        return None
    return zero / choice["val_loss"] - 1


#: ``margin(network, weights, spec, plant_dm_gain, dm_gain_model) -> (lower, upper)``: the stable DM-gain interval
#: (relative to the plant's gain) of ``network`` with ``weights`` in its loop, ``None`` if unstable. Built above the
#: training floor (:func:`eofnn.analysis.linear.dm_gain_margin`), which knows the stability analysis.
MarginFunction = Callable[..., "tuple[float, float] | None"]


def check_alpha_path(path: Sequence[float] | None, where: str = "optimization.") -> tuple[float, ...]:
    """The alpha path to search (the default when ``None``); one line unless increasing, finite and >= 0."""
    if path is None:
        return DEFAULT_ALPHA_PATH
    ok = isinstance(path, (list, tuple)) and len(path) >= 1 and all(
        isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) and a >= 0 for a in path)
    if not ok:
        raise ConfigError(f"{where}alpha_path={path!r} is invalid: it must be a non-empty list of finite alphas >= 0")
    if any(b <= a for a, b in zip(path[:-1], path[1:], strict=True)):
        raise ConfigError(f"{where}alpha_path={list(path)!r} is invalid: it must be strictly increasing")
    return tuple(float(a) for a in path)


def check_select(select: dict | None, where: str = "optimization.") -> tuple[float, float] | None:
    """The DM-gain interval a ``select: {dm_gain_interval: [low, high]}`` constraint asks for (``None``: none)."""
    if select is None:
        return None
    if not isinstance(select, dict) or set(select) != {"dm_gain_interval"}:
        raise ConfigError(f"{where}select={select!r} is invalid: the only constraint is {{dm_gain_interval: [low, "
                          "high]}}")
    interval = select["dm_gain_interval"]
    ok = (isinstance(interval, (list, tuple)) and len(interval) == 2
          and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in interval))
    if not ok or not 0 <= interval[0] < interval[1]:
        raise ConfigError(f"{where}select.dm_gain_interval={interval!r} is invalid: it must be two increasing finite "
                          "DM gains [low, high] with 0 <= low")
    if not interval[0] <= 1 <= interval[1]:
        raise ConfigError(f"{where}select.dm_gain_interval={list(interval)!r} is invalid: it must contain the nominal "
                          "DM gain 1")
    return float(interval[0]), float(interval[1])


@dataclass
class RidgePath:
    """Ridge solutions and validation errors along a path of alphas, from one eigendecomposition per group.

    Attributes
    ----------
    alphas : tuple of float
        The path (relative alphas when ``relative``).
    val_loss : list of float
        Mean squared validation error (nm² of command per sample and group) of each alpha; ``inf`` where the
        solution is not finite.
    """

    alphas: tuple[float, ...]
    val_loss: list[float]
    relative: bool
    _vectors: torch.Tensor = field(repr=False)
    _eigenvalues: torch.Tensor = field(repr=False)
    _rotated_cross: torch.Tensor = field(repr=False)
    _scale: torch.Tensor = field(repr=False)
    #: Validation error of the unregularised solution (alpha 0; ``inf`` where it is not finite).
    unregularised_loss: float = math.inf

    @classmethod
    def compute(cls, train, validation, alphas: Sequence[float], relative: bool = True) -> RidgePath:
        """The path over ``alphas`` of the normal equations ``train`` (a :class:`~eofnn.training.ridge.NormalEquations`),
        scored on the validation normal equations ``validation`` of the same features."""
        require(train.gram is not None, "no training data: the training stream yielded no batch")
        require(validation.gram is not None and validation.n_samples > 0,
                "alpha: auto needs validation data: the validation stream yielded no batch (give data.val_frames)")
        gram, scale = train.regular_gram(relative)
        eigenvalues, vectors = torch.linalg.eigh(gram)
        vt = vectors.transpose(1, 2)
        cross = (vt @ train.cross.unsqueeze(-1)).squeeze(-1)  # (groups, features)
        val_cross = (vt @ validation.cross.unsqueeze(-1)).squeeze(-1)
        val_gram = vt @ validation.gram @ vectors
        alpha = torch.tensor((*alphas, 0.0), dtype=torch.float64)  # and the unregularised limit, for the report
        denominator = eigenvalues.unsqueeze(1) + alpha.view(1, -1, 1) * scale.view(-1, 1, 1)  # (groups, A, features)
        rotated = cross.unsqueeze(1) / denominator.clamp(min=torch.finfo(torch.float64).tiny)
        sse = (validation.target_power.unsqueeze(1) - 2 * (rotated * val_cross.unsqueeze(1)).sum(-1)
               + torch.einsum("gaf,gfh,gah->ga", rotated, val_gram, rotated))
        loss = sse.sum(0) / (validation.n_samples * gram.shape[0])
        val_loss = [float(v) if math.isfinite(v) else math.inf for v in loss.tolist()]
        return cls(tuple(float(a) for a in alphas), val_loss[:-1], relative, vectors, eigenvalues, cross, scale,
                   val_loss[-1])

    @property
    def condition(self) -> float:
        """Largest condition number of the training Gram matrices over groups (before regularisation)."""
        eig = self._eigenvalues
        return float((eig[:, -1] / eig[:, 0].clamp(min=torch.finfo(torch.float64).tiny)).max())

    def weights(self, alpha: float) -> torch.Tensor:
        """``(groups, features)`` ridge solution at ``alpha`` (any alpha, not only those of the path)."""
        denominator = (self._eigenvalues + alpha * self._scale.unsqueeze(-1)).clamp(min=torch.finfo(torch.float64).tiny)
        return (self._vectors @ (self._rotated_cross / denominator).unsqueeze(-1)).squeeze(-1)

    def order(self) -> list[int]:
        """Indices of the path, least validation error first (ties: the larger alpha, the more robust)."""
        return sorted(range(len(self.alphas)), key=lambda i: (self.val_loss[i], -self.alphas[i]))

    def select(self, interval: tuple[float, float] | None = None, margin: MarginFunction | None = None) -> AlphaChoice:
        """The alpha of least validation error; with ``interval``, the least-error one whose stable DM-gain interval
        (from ``margin``) contains ``interval``. One line naming the widest interval reached when none does."""
        order = self.order()
        require(math.isfinite(self.val_loss[order[0]]), "every alpha of the path gave a non-finite solution: the "
                "training data is degenerate (all zero, or not finite)")
        if interval is None:
            return AlphaChoice(self.alphas[order[0]], self.val_loss[order[0]], self, None)
        require(margin is not None, "a DM-gain interval constraint needs the loop's stability analysis")
        widest: tuple[float, float, float] | None = None
        for i in order:
            if not math.isfinite(self.val_loss[i]):
                continue
            reached = margin(self.weights(self.alphas[i]))
            if reached is None:
                continue
            low, high = reached
            if low <= interval[0] and high >= interval[1]:
                return AlphaChoice(self.alphas[i], self.val_loss[i], self, (low, high))
            if widest is None or high - low > widest[1] - widest[0]:
                widest = (low, high, self.alphas[i])
        reach = ("no alpha gave a stable loop" if widest is None else
                 f"the widest reached is [{widest[0]:.3g}, {widest[1]:.3g}] at alpha={widest[2]:g}")
        raise ConfigError(f"optimization.select.dm_gain_interval={list(interval)!r} cannot be met on the alpha path "
                          f"{self.alphas[0]:g}..{self.alphas[-1]:g}: {reach}; widen the path or relax the interval")


@dataclass
class AlphaChoice:
    """The alpha chosen on validation data, its validation error, the path it came from and (under a robustness
    constraint) the stable DM-gain interval it reaches."""

    alpha: float
    val_loss: float
    path: RidgePath
    dm_gain_interval: tuple[float, float] | None = None

    def summary(self) -> dict:
        """JSON-ready: the choice and the validation curve."""
        out = {"alpha": self.alpha, "val_loss": self.val_loss, "relative": self.path.relative,
               "at_edge": self.alpha in (self.path.alphas[0], self.path.alphas[-1]),
               "unregularised_val_loss": (self.path.unregularised_loss if math.isfinite(self.path.unregularised_loss)
                                          else None),
               "path": {"alpha": list(self.path.alphas),
                        "val_loss": [v if math.isfinite(v) else None for v in self.path.val_loss]}}
        if self.dm_gain_interval is not None:
            out["dm_gain_interval"] = list(self.dm_gain_interval)
        return out
