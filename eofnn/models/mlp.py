"""A nonlinear baseline: an MLP over the same history tensors, weights shared across actuators."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from eofnn.errors import require
from eofnn.models.linear import gather_neighbourhood
from eofnn.sim.layout import layout_from_dict
from eofnn.validation import COUNT, POSITIVE, Interval, OneOf, check_value

ACTIVATIONS = {"gelu": nn.GELU, "relu": nn.ReLU, "tanh": nn.Tanh, "silu": nn.SiLU}


class MLP(nn.Module):
    """Per-actuator MLP that predicts the *change* of the wavefront over the loop delay.

    ``out = base(x) + w . f + scale * mlp(f / scale)`` where, for an open-loop history, ``base = -s_hat(n-d)``
    (the pseudo-integrator) and the features ``f`` are the frame-to-frame increments of the history; for a
    closed-loop history ``base = y(n-d) - eps(n-d)`` (the same pseudo-integrator, written with commands and
    residuals for a nominal DM) and ``f`` are the taps themselves. Predicting the increment keeps inputs and
    outputs at the scale of the servo-lag error (tens of nm) rather than the turbulence (µm), so gradient descent
    converges; the linear skip ``w`` lets it start from a linear predictor, the MLP learns what is left.
    Zero-initialised output layers make the untrained network the pseudo-integrator.

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
    history_kind : {"open_loop", "closed_loop"}
        Kind of history the network reads (set by eofnn from the history spec).
    delay_frames : int or float
        Loop delay (set by eofnn from the history spec); the base reads its whole frames.
    scale_nm : float
        Typical magnitude of the features in nm.
    """

    def __init__(self, n_taps: int, hidden: Sequence[int] = (64, 64), activation: str = "gelu", radius: float = 0.0,
                 grid: dict | None = None, n_actuators: int | None = None, history_kind: str = "open_loop",
                 delay_frames: int | float = 2, scale_nm: float = 10.0) -> None:
        super().__init__()
        check_value("activation", activation, OneOf(tuple(ACTIVATIONS)))
        check_value("scale_nm", scale_nm, POSITIVE)
        check_value("history_kind", history_kind, OneOf(("open_loop", "closed_loop")))
        check_value("radius", radius, Interval(0, 64, unit="pitches"))
        require(isinstance(hidden, Sequence) and all(COUNT.accepts(h) for h in hidden),
                f"hidden={hidden!r} is invalid: it must be a list of layer widths >= 1")
        p = n_taps // 2 if history_kind == "closed_loop" else n_taps
        require(history_kind == "open_loop" or math.floor(delay_frames) <= p,
                f"a closed-loop MLP needs history_length >= delay_frames, got {p} < {math.floor(delay_frames)}")
        self.history_kind, self.delay_frames, self.history_length = history_kind, delay_frames, p
        self.scale_nm = scale_nm
        per_actuator = n_taps - 1 if history_kind == "open_loop" else n_taps
        n_inputs = per_actuator
        self.register_buffer("neighbours", None)  # a buffer from the start, so a neighbourhood can replace it
        if radius > 0:
            require(grid is not None, "an MLP with radius > 0 needs the actuator grid")
            neighbours = layout_from_dict(grid).neighbours(radius)
            if n_actuators is not None:
                require(neighbours.shape[0] == n_actuators,
                        f"grid has {neighbours.shape[0]} actuators but n_actuators={n_actuators}")
            self.register_buffer("neighbours", neighbours)
            n_inputs = per_actuator * neighbours.shape[1]
        self.skip = nn.Linear(max(n_inputs, 1), 1, bias=False)
        nn.init.zeros_(self.skip.weight)
        layers: list[nn.Module] = []
        width = max(n_inputs, 1)
        for h in hidden:
            layers += [nn.Linear(width, h), ACTIVATIONS[activation]()]
            width = h
        last = nn.Linear(width, 1)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(*layers, last)

    #: Histories come in float64: the base (the pseudo-integrator) is exact, only the learned correction is float32.
    input_dtype = torch.float64

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        x = history.to(torch.float64)  # the base is exact; only the learned correction runs in float32
        if self.history_kind == "open_loop":
            base = -x[..., 0]
            features = x[..., :-1] - x[..., 1:]
        else:
            # -s_hat(n - d) with the whole frames d of the delay (for a fractional one, the learnt part corrects it).
            p, d = self.history_length, math.floor(self.delay_frames)
            base = x[..., d - 1] - x[..., p]
            features = x
        if features.shape[-1] == 0:
            features = torch.zeros_like(x[..., :1])
        if self.neighbours is not None:
            features = gather_neighbourhood(features, self.neighbours)
        f = features.to(self.skip.weight.dtype)
        correction = self.skip(f).squeeze(-1) + self.scale_nm * self.mlp(f / self.scale_nm).squeeze(-1)
        return base + correction.to(torch.float64)
