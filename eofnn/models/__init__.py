"""Predictors (plain ``torch.nn.Module`` networks over history tensors) and the controllers that run them."""

from __future__ import annotations

from eofnn.models.controllers import Dithered, Integrator, PseudoIntegrator, Uncorrected, critical_gain
from eofnn.models.linear import ClosedLoopEOF, LinearFilter, OpenLoopEOF
from eofnn.models.mlp import MLP
from eofnn.models.predictive import PredictiveController

__all__ = [
    "MLP", "ClosedLoopEOF", "Dithered", "Integrator", "LinearFilter", "OpenLoopEOF", "PredictiveController",
    "PseudoIntegrator", "Uncorrected", "critical_gain",
]
