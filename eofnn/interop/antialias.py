"""Deprecated alias: this module moved to :mod:`eofnn.studies.antialias` (``docs/design.md``, "Floors": ``interop`` keeps the
adapters). Importing it here warns once (DeprecationWarning) and gives the moved module itself; it goes in the next
release."""

import sys
import warnings

import eofnn.studies.antialias as _moved

warnings.warn("eofnn.interop.antialias moved to eofnn.studies.antialias; the old path goes in the next release",
              DeprecationWarning, stacklevel=2)
sys.modules[__name__] = _moved
