"""Predictors: plain ``torch.nn.Module`` networks over history tensors (no Lightning, no loop-side state)."""

from __future__ import annotations

from eofnn.models.linear import ClosedLoopEOF, LinearFilter, OpenLoopEOF
from eofnn.models.mlp import MLP

__all__ = ["MLP", "ClosedLoopEOF", "LinearFilter", "OpenLoopEOF"]
