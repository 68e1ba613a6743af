"""Telemetry: what a loop records (``s, y, eps, wfs``, its delay and layout) in memory and on disk, and other systems'
files (FITS, npz; slopes with an interaction matrix or reconstructor, modal coefficients). Data I/O, below the
simulation: the loop writes a :class:`Telemetry`, the commands read one; nothing here simulates. ``Telemetry`` is
imported when first read (:func:`eofnn.lazy.lazy_exports`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eofnn.lazy import lazy_exports

if TYPE_CHECKING:
    from eofnn.telemetry.record import Telemetry

__getattr__, __dir__ = lazy_exports(__name__, {"Telemetry": "eofnn.telemetry.record"})

__all__ = ["Telemetry"]
