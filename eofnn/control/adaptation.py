"""The configuration of online adaptation: a fitted per-actuator filter keeps learning from telemetry in the loop."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import eofnn
from eofnn.errors import ConfigError
from eofnn.validation import COUNT, FRACTION, NON_NEGATIVE, Constraint, Interval, OneOf, validated

# The controllers (torch) are imported when one is built, not with the config; the annotation names them by path:
# jsonargparse runs a config module's TYPE_CHECKING imports when it reads the config's types.

METHODS = ("none", "rls", "blend")


@dataclass
@validated
class AdaptationConfig:
    """How a predictor adapts while the loop runs (from telemetry alone), with a fallback to an integrator.

    Parameters
    ----------
    method : {"none", "rls", "blend"}
        ``rls``: recursive least squares every frame; ``blend``: every ``every_frames`` frames a ridge fit on the
        last ``window_frames`` frames, blended in with ``gain`` (cacao's recompute-and-blend).
    forgetting : float
        RLS forgetting factor in (0, 1] (memory of about ``1 / (1 - forgetting)`` frames).
    every_frames : int
        Frames between blend refits.
    window_frames : int
        Frames of telemetry each blend refit uses (at least ``every_frames``).
    gain : float
        Blend gain in (0, 1]: ``W <- (1 - gain) W + gain W_new``.
    alpha : float
        Ridge parameter of the blend refits (relative).
    dither_nm : float
        RMS white dither added to the commands (excitation for closed-loop identification).
    integrator_gain : float
        Gain of the integrator the loop falls back to when it starts to diverge.
    fallback_factor : float
        The fallback engages when the residual RMS exceeds this times its running median.
    """

    method: str = "none"
    forgetting: float = 0.999
    every_frames: int = 500
    window_frames: int = 2000
    gain: float = 0.2
    alpha: float = 1e-6
    dither_nm: float = 0.0
    integrator_gain: float = 0.5
    fallback_factor: float = 10.0

    _constraints: ClassVar[dict[str, Constraint]] = {
        "method": OneOf(METHODS),
        "forgetting": FRACTION,
        "every_frames": COUNT,
        "window_frames": COUNT,
        "gain": FRACTION,
        "alpha": NON_NEGATIVE,
        "dither_nm": Interval(0, 1e5, unit="nm"),
        "integrator_gain": Interval(0, 10),
        "fallback_factor": Interval(1, 1e6, closed="neither"),
    }
    _where: ClassVar[str] = "adaptation."

    def __post_init__(self) -> None:
        if self.window_frames < self.every_frames:
            raise ConfigError(f"adaptation.window_frames={self.window_frames} is invalid: it must be at least "
                              f"adaptation.every_frames={self.every_frames}")

    def build(self, predictor: Any, dm_gain_model: float) -> eofnn.control.adaptive.AdaptiveController:
        """The adaptive controller that starts from ``predictor``'s fitted per-actuator filter."""
        from eofnn.control.adaptive import BlendController, RLSController

        network = predictor.network
        if getattr(network, "structure", None) != "per_actuator":
            raise ConfigError(f"adaptation.method={self.method!r} adapts a per-actuator linear filter; this predictor "
                              f"is a {type(network).__name__} ({getattr(network, 'structure', 'not linear')})")
        common = {"dm_gain_model": dm_gain_model, "dither_nm": self.dither_nm,
                  "integrator_gain": self.integrator_gain, "fallback_factor": self.fallback_factor}
        if self.method == "rls":
            return RLSController(predictor.spec, network.weight, forgetting=self.forgetting, **common)
        return BlendController(predictor.spec, network.weight, every_frames=self.every_frames,
                               window_frames=self.window_frames, gain=self.gain, alpha=self.alpha, **common)
