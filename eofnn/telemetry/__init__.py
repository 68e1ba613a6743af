"""Telemetry: what a loop records (``s, y, eps, wfs``, its delay and layout) in memory and on disk, and other systems'
files (FITS, npz; slopes with an interaction matrix or reconstructor, modal coefficients). Data I/O, below the
simulation: the loop writes a :class:`Telemetry`, the commands read one; nothing here simulates."""

from __future__ import annotations

from eofnn.telemetry.record import Telemetry

__all__ = ["Telemetry"]
