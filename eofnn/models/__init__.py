"""Predictors: plain ``torch.nn.Module`` networks over history tensors (no Lightning, no loop-side state). The
networks are imported when first read (:func:`eofnn.lazy.lazy_exports`): ``eofnn.models.build``'s names alone
need no torch."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eofnn.lazy import lazy_exports

if TYPE_CHECKING:
    from eofnn.models.linear import ClosedLoopEOF, LinearFilter, OpenLoopEOF
    from eofnn.models.mlp import MLP

__getattr__, __dir__ = lazy_exports(__name__, {
    **dict.fromkeys(("ClosedLoopEOF", "LinearFilter", "OpenLoopEOF"), "eofnn.models.linear"), "MLP": "eofnn.models.mlp",
})

__all__ = ["MLP", "ClosedLoopEOF", "LinearFilter", "OpenLoopEOF"]
