"""Linear predictors over history tensors: the EOF filters of the study and their relatives.

A :class:`LinearFilter` maps a history ``(batch, K, taps)`` to commands ``(batch, K)`` with one of four structures:

- ``per_actuator``: one filter per actuator (the study),
- ``shared``: one filter for all actuators,
- ``neighbourhood``: each actuator's filter reads the histories of the actuators within ``radius`` pitches
  (Guyon & Males 2017); slots beyond the pupil edge read zeros;
- ``modal``: one temporal filter per Karhunen-Loeve mode of Kolmogorov turbulence on the layout
  (:func:`kolmogorov_modes`; van Kooten et al. 2020 predict per mode): ``y = B (w_m . (B^T h)_m)_m``. The basis is
  orthonormal and complete, so white noise stays white and equal in every mode, and with a DM that acts as ``g y``
  the modes decouple in the loop as actuators do.

Linear filters can be fitted in closed form: :meth:`features` and :meth:`group_targets` give the regression
problem per *group* (an actuator, a mode, or everything for ``shared``) and :meth:`load_solution` sets the weights.
"""

from __future__ import annotations

import torch
from torch import nn

from eofnn.errors import require
from eofnn.sim.layout import layout_from_dict
from eofnn.validation import COUNT, Interval, OneOf, check_value

STRUCTURES = ("per_actuator", "shared", "neighbourhood", "modal")


def kolmogorov_modes(positions_m) -> torch.Tensor:
    """``(K, K)`` orthonormal columns: the Karhunen-Loeve modes of Kolmogorov turbulence sampled at ``positions_m``
    ``(K, 2)`` (metres), by decreasing variance, piston last.

    The phase covariance of Kolmogorov turbulence diverges, its piston-removed form does not: the modes are the
    eigenvectors of ``P (-D / 2) P`` with ``D_ij = |r_i - r_j|^(5/3)`` (the structure function up to its scale, which
    the modes do not depend on) and ``P = I - 1 1^T / K``. Each column's sign makes its largest entry positive, so the
    basis is a function of the layout alone.
    """
    pos = torch.as_tensor(positions_m, dtype=torch.float64)
    distance = torch.cdist(pos, pos)
    k = pos.shape[0]
    centring = torch.eye(k, dtype=torch.float64) - 1.0 / k
    values, vectors = torch.linalg.eigh(centring @ (-0.5 * distance.pow(5.0 / 3.0)) @ centring)
    vectors = vectors[:, values.argsort(descending=True)]
    largest = vectors.gather(0, vectors.abs().argmax(0, keepdim=True))
    return vectors * largest.sign()


def gather_neighbourhood(x: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """``(batch, K, M * taps)``: each actuator's ``(batch, K, taps)`` history beside its ``M`` neighbours'.

    ``neighbours`` is :meth:`ActuatorGrid.neighbours` or :meth:`ActuatorLayout.neighbours`; its off-pupil slots
    (index ``K``) read zeros.
    """
    padded = torch.cat([x, torch.zeros_like(x[:, :1])], dim=1)
    if x.requires_grad:  # the gradient of advanced indexing, as it always was
        return padded[:, neighbours].flatten(-2)
    # The same copy, by index_select: under half the time of advanced indexing (it runs every frame of a loop).
    return padded.index_select(1, neighbours.flatten()).unflatten(1, neighbours.shape).flatten(-2)


class LinearFilter(nn.Module):
    """Linear map from a history tensor to commands.

    Parameters
    ----------
    n_actuators : int
        Active actuators ``K``.
    n_taps : int
        Taps per actuator in the history.
    structure : {"per_actuator", "shared", "neighbourhood", "modal"}
        How filters are shared between actuators (``modal``: one per Kolmogorov KL mode of the layout).
    radius : float
        Neighbourhood radius in pitches (``neighbourhood`` only).
    grid : dict, optional
        The layout, needed for ``neighbourhood``: the :class:`~eofnn.sim.grid.ActuatorGrid` fields (``diameter_m``,
        ``n_across``, ``obstruction``) or ``{"positions_m": [[x, y], ...]}`` (metres, any layout: neighbours by
        distance, :class:`~eofnn.sim.layout.ActuatorLayout`).
    """

    def __init__(self, n_actuators: int, n_taps: int, structure: str = "per_actuator", radius: float = 1.0,
                 grid: dict | None = None) -> None:
        super().__init__()
        check_value("structure", structure, OneOf(STRUCTURES))
        check_value("n_actuators", n_actuators, COUNT)
        check_value("n_taps", n_taps, COUNT)
        check_value("radius", radius, Interval(0, 64, unit="pitches"))
        self.n_actuators, self.n_taps, self.structure, self.radius = n_actuators, n_taps, structure, radius
        if structure == "neighbourhood":
            require(grid is not None, "structure='neighbourhood' needs the actuator grid")
            neighbours = layout_from_dict(grid).neighbours(radius)
            require(neighbours.shape[0] == n_actuators,
                    f"grid has {neighbours.shape[0]} actuators but n_actuators={n_actuators}")
            self.register_buffer("neighbours", neighbours)
            shape = (n_actuators, neighbours.shape[1] * n_taps)
        elif structure == "modal":
            require(grid is not None, "structure='modal' needs the actuator grid (its modes are the layout's)")
            positions = layout_from_dict(grid).positions_m
            require(len(positions) == n_actuators, f"grid has {len(positions)} actuators but n_actuators={n_actuators}")
            self.register_buffer("modes", kolmogorov_modes(positions))
            shape = (n_actuators, n_taps)
        elif structure == "shared":
            shape = (1, n_taps)
        else:
            shape = (n_actuators, n_taps)
        self.weight = nn.Parameter(torch.zeros(shape, dtype=torch.float64))

    def _inputs(self, history: torch.Tensor) -> torch.Tensor:
        """``(batch, K, features)``: the history itself, the neighbourhood histories side by side, or the modes'."""
        if self.structure == "modal":
            return torch.einsum("km,bkt->bmt", self.modes.to(history.dtype), history)
        return gather_neighbourhood(history, self.neighbours) if self.structure == "neighbourhood" else history

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        x = self._inputs(history.to(self.weight.dtype))
        out = (x * self.weight).sum(-1)
        return out @ self.modes.T.to(out.dtype) if self.structure == "modal" else out

    # -- closed-form fitting -------------------------------------------------------------------------------------
    def features(self, history: torch.Tensor) -> torch.Tensor:
        """Regressors per group, ``(groups, samples, features)``."""
        x = self._inputs(history.to(self.weight.dtype))
        if self.structure == "shared":
            return x.reshape(1, -1, x.shape[-1])
        return x.transpose(0, 1)

    def group_targets(self, target: torch.Tensor) -> torch.Tensor:
        """Targets per group, ``(groups, samples)``, matching :meth:`features`."""
        target = target.to(self.weight.dtype)
        if self.structure == "modal":  # the modes' targets: the loss in actuators is their sum (orthonormal basis)
            target = target @ self.modes.to(target.dtype)
        return target.reshape(1, -1) if self.structure == "shared" else target.transpose(0, 1)

    @torch.no_grad()
    def load_solution(self, solution: torch.Tensor) -> None:
        """Set the weights from a ``(groups, features)`` solution (overwrites any previous fit)."""
        require(tuple(solution.shape) == tuple(self.weight.shape),
                f"solution has shape {tuple(solution.shape)}, expected {tuple(self.weight.shape)}")
        self.weight.copy_(solution)


class OpenLoopEOF(LinearFilter):
    """Open-loop (pseudo-open-loop) EOF, a :class:`LinearFilter` on open-loop histories:
    ``y(n) = -F . [s_hat(n-d), ..., s_hat(n-d-p+1)]``."""


class ClosedLoopEOF(LinearFilter):
    """Closed-loop EOF, a :class:`LinearFilter` on closed-loop histories:
    ``y(n) = theta . [y(n-1..n-p), eps(n-d..n-d-p+1)]``."""
