"""Values the controllers' configs accept, free of torch: the command line checks a config against them before the
controllers (:mod:`eofnn.control.classical`, which re-exports them) are imported."""

from __future__ import annotations

#: Polynomial orders of the POL extrapolator: 0 is a POL zero-order hold, 1 linear, 2 quadratic.
EXTRAPOLATION_ORDERS = (0, 1, 2)

__all__ = ["EXTRAPOLATION_ORDERS"]
