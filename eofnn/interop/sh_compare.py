"""Deprecated alias: this module moved to :mod:`eofnn.studies.sh_compare` (``docs/design.md``, "Floors": ``interop`` keeps the
adapters). Importing it here warns once (DeprecationWarning) and gives the moved module itself; it goes in the next
release."""

import sys
import warnings

import eofnn.studies.sh_compare as _moved

warnings.warn("eofnn.interop.sh_compare moved to eofnn.studies.sh_compare; the old path goes in the next release",
              DeprecationWarning, stacklevel=2)
sys.modules[__name__] = _moved
