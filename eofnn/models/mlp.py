"""A nonlinear baseline: an MLP over the same history tensors, weights shared across actuators."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from eofnn.errors import require
from eofnn.sim.grid import ActuatorGrid

ACTIVATIONS = {"gelu": nn.GELU, "relu": nn.ReLU, "tanh": nn.Tanh, "silu": nn.SiLU}


class MLP(nn.Module):
    """Per-actuator MLP with a linear skip: ``out = w . x + scale * mlp(x / scale)``.

    The linear skip lets the network start from (and stay close to) a shared linear filter, so SGD does not have
    to rediscover linear extrapolation; the MLP learns what is left. Inputs are divided by ``scale_nm`` so the
    hidden layers see order-one values.

    Parameters
    ----------
    n_taps : int
        Taps per actuator in the history.
    hidden : sequence of int
        Hidden layer widths.
    activation : str
        One of ``gelu``, ``relu``, ``tanh``, ``silu``.
    radius : float
        Neighbourhood radius in pitches; 0 uses each actuator's own history only.
    grid : dict, optional
        :class:`ActuatorGrid` fields, needed when ``radius > 0``.
    n_actuators : int, optional
        Active actuators (checked against the grid when a neighbourhood is used).
    scale_nm : float
        Typical magnitude of the inputs in nm.
    """

    def __init__(self, n_taps: int, hidden: Sequence[int] = (64, 64), activation: str = "gelu", radius: float = 0.0,
                 grid: dict | None = None, n_actuators: int | None = None, scale_nm: float = 100.0) -> None:
        super().__init__()
        require(activation in ACTIVATIONS,
                f"activation={activation!r} is invalid: allowed are {', '.join(ACTIVATIONS)}")
        require(scale_nm > 0, f"scale_nm={scale_nm!r} is invalid: it must be > 0")
        self.scale_nm = scale_nm
        n_inputs = n_taps
        self.neighbours = None
        if radius > 0:
            require(grid is not None, "an MLP with radius > 0 needs the actuator grid")
            neighbours = ActuatorGrid(**grid).neighbours(radius)
            if n_actuators is not None:
                require(neighbours.shape[0] == n_actuators,
                        f"grid has {neighbours.shape[0]} actuators but n_actuators={n_actuators}")
            self.register_buffer("neighbours", neighbours)
            n_inputs = n_taps * neighbours.shape[1]
        self.skip = nn.Linear(n_inputs, 1, bias=False)
        nn.init.zeros_(self.skip.weight)
        layers: list[nn.Module] = []
        width = n_inputs
        for h in hidden:
            layers += [nn.Linear(width, h), ACTIVATIONS[activation]()]
            width = h
        last = nn.Linear(width, 1)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(*layers, last)

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        x = history.to(self.skip.weight.dtype)
        if self.neighbours is not None:
            padded = torch.cat([x, torch.zeros_like(x[:, :1])], dim=1)
            x = padded[:, self.neighbours].flatten(-2)
        return self.skip(x).squeeze(-1) + self.scale_nm * self.mlp(x / self.scale_nm).squeeze(-1)
