"""The loop delay ``tau = d + f`` in frames, integer or fractional, and its two parts.

Convention (the same as :func:`eofnn.analysis.polynomials.fractional_delay`): with ``d = floor(tau)`` and
``f = tau - d``, the controller computing ``y(n)`` receives the WFS reading of ``eps(n - d)``, and the DM shape
acting during frame ``n`` is the time average of the commands over it, ``(1 - f) DM(y(n)) + f DM(y(n - 1))``
(a fraction ``f`` of the frame still sees the previous command). The plant is ``z^-d ((1 - f) + f z^-1)``;
``f = 0`` is today's integer delay.
"""

from __future__ import annotations

import math

from eofnn.validation import Interval, check_value

#: What a loop delay may be: any finite number of frames in [1, 100] (fractional allowed).
DELAY = Interval(1, 100, unit="frames")


def check_delay(value, name: str = "delay_frames", where: str = "") -> int | float:
    """``value`` checked against :data:`DELAY`; an integral value comes back as an ``int`` (``2.0`` -> ``2``)."""
    check_value(name, value, DELAY, where)
    return int(value) if float(value).is_integer() else float(value)


def split_delay(delay_frames: float) -> tuple[int, float]:
    """``(d, f)``: whole frames ``d = floor(tau)`` (the lag of the WFS reading) and the fraction ``f = tau - d``."""
    d = math.floor(delay_frames)
    return d, float(delay_frames) - d
