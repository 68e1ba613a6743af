"""Values the controllers' configs accept, free of torch: the command line checks a config against them before the
controllers (:mod:`eofnn.control.classical`, which re-exports them) are imported; and the configuration of
predictive Fourier control (:class:`PfcConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from eofnn.errors import ConfigError
from eofnn.validation import Constraint, Interval, validated

#: Polynomial orders of the POL extrapolator: 0 is a POL zero-order hold, 1 linear, 2 quadratic.
EXTRAPOLATION_ORDERS = (0, 1, 2)
#: The most extra POL frames an extrapolator's least-squares fit may average over (``smoothing``).
MAX_EXTRAPOLATION_SMOOTHING = 16
#: Orders of the per-mode autoregressive model of an LQG controller (:mod:`eofnn.control.kalman`).
AR_ORDERS = (1, 2)
#: The most frozen-flow layers a predictive Fourier controller models.
MAX_PFC_LAYERS = 4


@dataclass
@validated
class PfcConfig:
    """Predictive Fourier control (``controller: pfc``, :mod:`eofnn.control.fourier`): a Kalman filter per spatial
    Fourier mode whose state model is frozen-flow translation by each layer's wind.

    Parameters
    ----------
    layers : int
        Frozen-flow layers identified from the telemetry (their winds and weights, :mod:`eofnn.control.wind`);
        a layer the telemetry does not support (weight below 10%) is dropped.
    winds : list of [speed_mps, direction_deg, weight], optional
        Known layers instead of identified ones (e.g. from a profiler): speed in m/s, the direction the screen moves
        towards in degrees from +x towards +y, and the layer's share of the turbulence (weights are normalised).
    alpha : float
        Modulus of each state's frozen-flow rotation per frame, ``a(n + 1) = alpha exp(-2 pi i k.v T) a(n)``: below
        1 for stability, and the memory of the filter (about ``1 / (1 - alpha)`` frames). The prediction over the
        delay is shrunk by ``alpha^d``, a bias of ``(1 - alpha^d)`` times the turbulence: keep it close to 1.
    aliases : int
        Rings of aliased frequencies ``k + m / pitch`` (``|m_x|, |m_y| <= aliases``) in each mode's state: the
        actuator grid samples a field that is not band-limited, and its aliases move at their own temporal
        frequency (0: one state per layer, the scalar filter).
    padding : float
        Size of the FFT grid over the actuator grid's (at least 1; odd sizes: no Nyquist bin).
    max_speed_mps : float
        Fastest wind the identification searches for, m/s.
    """

    layers: int = 2
    winds: list[list[float]] | None = None
    alpha: float = 0.9999
    aliases: int = 1
    padding: float = 2.0
    max_speed_mps: float = 50.0

    _constraints: ClassVar[dict[str, Constraint]] = {
        "layers": Interval(1, MAX_PFC_LAYERS, integer=True, unit="frozen-flow layers"),
        "alpha": Interval(0.5, 1, closed="left"),
        "aliases": Interval(0, 2, integer=True, unit="rings of aliased frequencies"),
        "padding": Interval(1, 4, unit="FFT grid over the actuator grid"),
        "max_speed_mps": Interval(0, 1000, closed="right", unit="m/s"),
    }
    _where: ClassVar[str] = "pfc."

    def __post_init__(self) -> None:
        if self.winds is None:
            return
        shape = "a non-empty list of [speed_mps, direction_deg, weight] (at most {MAX_PFC_LAYERS} layers)"
        if not isinstance(self.winds, (list, tuple)) or not 1 <= len(self.winds) <= MAX_PFC_LAYERS:
            raise ConfigError(f"pfc.winds={self.winds!r} is invalid: it must be {shape.format(**globals())}")
        for wind in self.winds:
            numbers = isinstance(wind, (list, tuple)) and len(wind) == 3 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in wind)
            if not numbers or not 0 <= wind[0] <= 1000 or wind[2] <= 0:
                raise ConfigError(f"pfc.winds={self.winds!r} is invalid: {wind!r} is not [speed_mps in [0, 1000], "
                                  "direction_deg, weight > 0]")


__all__ = ["AR_ORDERS", "EXTRAPOLATION_ORDERS", "MAX_EXTRAPOLATION_SMOOTHING", "MAX_PFC_LAYERS", "PfcConfig"]
