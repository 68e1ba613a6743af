"""Deprecated alias: this module moved to :mod:`eofnn.studies.study` (``docs/design.md``, "Floors": ``interop`` keeps the
adapters). Importing it here warns once (DeprecationWarning) and gives the moved module itself; it goes in the next
release."""

import sys
import warnings

import eofnn.studies.study as _moved

warnings.warn("eofnn.interop.study moved to eofnn.studies.study; the old path goes in the next release",
              DeprecationWarning, stacklevel=2)
sys.modules[__name__] = _moved
