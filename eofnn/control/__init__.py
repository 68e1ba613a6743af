"""Loop-side controllers: baselines, dither, predictive controllers with ring buffers, built by one registry."""

from __future__ import annotations

from eofnn.control.baselines import Dithered, Integrator, PseudoIntegrator, Uncorrected, critical_gain
from eofnn.control.predictive import HistoryRing, PredictiveController
from eofnn.control.registry import build_controller, controller_names, register_controller

__all__ = [
    "Dithered", "HistoryRing", "Integrator", "PredictiveController", "PseudoIntegrator", "Uncorrected",
    "build_controller", "controller_names", "critical_gain", "register_controller",
]
