"""Deprecated alias: this module moved to :mod:`eofnn.studies.report` (``docs/design.md``, "Floors": ``interop`` keeps the
adapters). Importing it here warns once (DeprecationWarning) and gives the moved module itself; it goes in the next
release."""

import sys
import warnings

import eofnn.studies.report as _moved

warnings.warn("eofnn.interop.report moved to eofnn.studies.report; the old path goes in the next release",
              DeprecationWarning, stacklevel=2)
sys.modules[__name__] = _moved
