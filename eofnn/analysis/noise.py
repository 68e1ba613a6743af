"""How much white measurement noise a linear controller returns to the residual: its noise gain.

A loop whose command ``y`` is driven by a measurement ``m`` carrying white noise ``w`` of variance ``sigma²`` puts
``sigma² sum_n h(n)²`` of it on the residual, ``h`` the closed loop's impulse response from ``w`` to ``y`` (the
residual is ``s + y``, and the noise enters it only through the command). That sum, the *noise gain*, is the share
of the measurement's white noise power (photon and read noise, and aliasing as far as it is white) the loop keeps.
"""

from __future__ import annotations

import math

import numpy as np

from eofnn.errors import require

#: Samples of the impulse response summed.
IMPULSE_SAMPLES = 20001


def integrator_noise_gain(loop_gain: float, delay_frames: int = 2) -> float:
    """The noise gain of the integrator ``y(n) = y(n-1) - k m(n-d)`` of loop gain ``k``, ``m = s + y + w``.

    The transfer from the noise ``w`` to the command is ``-k z^-d / (1 - z^-1 + k z^-d)``; its squared impulse
    response is summed over :data:`IMPULSE_SAMPLES` samples. In closed form, ``k / (2 - k)`` at ``d = 1`` and
    ``k (1 + k) / ((1 - k) (2 + k))`` at ``d = 2`` (the variance of an AR(2) process), which the tests check.

    Parameters
    ----------
    loop_gain : float
        ``k``: the integrator's gain times the loop's DM and optical gain (dimensionless), positive.
    delay_frames : int
        ``d``: whole frames between the measurement and the command it drives (at least 1).

    Returns
    -------
    float
        The share of the measurement's white noise power returned to the residual (dimensionless);
        ``inf`` for a loop gain at or past the stability limit (``2`` at ``d = 1``, ``1`` at ``d = 2``).
    """
    from scipy.signal import lfilter

    require(isinstance(delay_frames, int) and delay_frames >= 1,
            f"delay_frames must be a whole number of frames, at least 1: got {delay_frames!r}")
    require(math.isfinite(loop_gain) and loop_gain > 0, f"loop_gain must be positive and finite: got {loop_gain!r}")
    impulse = [1.0] + [0.0] * (IMPULSE_SAMPLES - 1)
    numerator = [0.0] * delay_frames + [-loop_gain]
    denominator = [1.0, -1.0] + [0.0] * (delay_frames - 1)
    denominator[delay_frames] += loop_gain
    if np.abs(np.roots(denominator)).max() >= 1.0:
        return math.inf
    return float(sum(v * v for v in lfilter(numerator, denominator, impulse)))
