"""eofnn: predictive wavefront control for adaptive optics, in simulated closed loop."""

from __future__ import annotations

__version__ = "0.1.0"
