"""Loop-side controllers: baselines, dither, predictive controllers with ring buffers, built by one registry. The
names below are imported when first read (:func:`eofnn.lazy.lazy_exports`): the registry's names, which the command
line's parser lists, come without the controllers' torch."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eofnn.lazy import lazy_exports

if TYPE_CHECKING:
    from eofnn.control.baselines import Dithered, Integrator, PseudoIntegrator, Uncorrected, critical_gain
    from eofnn.control.predictive import HistoryRing, PredictiveController
    from eofnn.control.registry import build_controller, controller_names, register_controller

__getattr__, __dir__ = lazy_exports(__name__, {
    **dict.fromkeys(("Dithered", "Integrator", "PseudoIntegrator", "Uncorrected", "critical_gain"),
                    "eofnn.control.baselines"),
    **dict.fromkeys(("HistoryRing", "PredictiveController"), "eofnn.control.predictive"),
    **dict.fromkeys(("build_controller", "controller_names", "register_controller"), "eofnn.control.registry"),
})

__all__ = [
    "Dithered", "HistoryRing", "Integrator", "PredictiveController", "PseudoIntegrator", "Uncorrected",
    "build_controller", "controller_names", "critical_gain", "register_controller",
]
