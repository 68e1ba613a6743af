"""A user's own predictor, plugged into eofnn by class_path (see tests/test_cli.py)."""

from __future__ import annotations

import torch
from torch import nn


class TapMixer(nn.Module):
    """One learned weight per tap shared by all actuators: ``y = -(w . history)``, initialised to the last value."""

    def __init__(self, n_taps: int) -> None:
        super().__init__()
        init = torch.zeros(n_taps)
        init[0] = 1.0
        self.weights = nn.Parameter(init)

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        return -(history.to(self.weights.dtype) * self.weights).sum(-1)
