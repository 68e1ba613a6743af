"""Values the controllers' configs accept, free of torch: the command line checks a config against them before the
controllers (:mod:`eofnn.control.classical`, which re-exports them) are imported."""

from __future__ import annotations

#: Polynomial orders of the POL extrapolator: 0 is a POL zero-order hold, 1 linear, 2 quadratic.
EXTRAPOLATION_ORDERS = (0, 1, 2)
#: The most extra POL frames an extrapolator's least-squares fit may average over (``smoothing``).
MAX_EXTRAPOLATION_SMOOTHING = 16
#: Orders of the per-mode autoregressive model of an LQG controller (:mod:`eofnn.control.kalman`).
AR_ORDERS = (1, 2)

__all__ = ["AR_ORDERS", "EXTRAPOLATION_ORDERS", "MAX_EXTRAPOLATION_SMOOTHING"]
