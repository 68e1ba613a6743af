"""A user's network seen through input and target scales, so gradient descent works on numbers of order one.

Histories and targets are nm of optical path, often micrometres: a network initialised for inputs of order one
(torch's default) sees inputs a thousand times too large and must output numbers a thousand times larger than its
initial weights give, and gradient descent at ordinary learning rates barely moves it. :class:`Normalized` divides
the history by ``input_scale_nm`` and multiplies the output by ``target_scale_nm`` (both RMS values measured on the
first training batch, then kept as buffers, so the checkpoint restores them). eofnn's own networks scale
themselves (the MLP) or are fitted in closed form, so they are not wrapped.
"""

from __future__ import annotations

import torch
from torch import nn


class Normalized(nn.Module):
    """``y = target_scale_nm * inner(history / input_scale_nm)``.

    Parameters
    ----------
    inner : nn.Module
        The network, mapping ``(batch, K, taps)`` to ``(batch, K)``.
    """

    def __init__(self, inner: nn.Module) -> None:
        super().__init__()
        self.inner = inner
        self.register_buffer("input_scale_nm", torch.ones((), dtype=torch.float64))
        self.register_buffer("target_scale_nm", torch.ones((), dtype=torch.float64))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))

    @property
    def input_dtype(self) -> torch.dtype:
        declared = getattr(self.inner, "input_dtype", None)
        if declared is not None:
            return declared
        first = next(self.inner.parameters(), None)
        return torch.float64 if first is None else first.dtype

    @torch.no_grad()
    def fit_scales(self, history: torch.Tensor, target: torch.Tensor) -> None:
        """Set both scales from one batch (RMS, nm); a zero RMS keeps the scale 1."""
        for buffer, value in ((self.input_scale_nm, history), (self.target_scale_nm, target)):
            rms = value.to(torch.float64).pow(2).mean().sqrt()
            buffer.fill_(float(rms) if torch.isfinite(rms) and rms > 0 else 1.0)
        self.fitted.fill_(True)

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        scaled = (history / self.input_scale_nm).to(self.input_dtype)
        return self.inner(scaled) * self.target_scale_nm.to(self.input_dtype)
