"""What the stability analysis refuses in the filters it is given, checked once on the way in: a filter of any
structure (:func:`check_weights`, for :func:`~eofnn.analysis.stability.analyse`), or a fitted
:class:`~eofnn.models.linear.LinearFilter` and the histories it reads (:func:`check_filter`, whose structure and
shape its own construction fixed). Weights the analysis builds itself (an integrator's) are not checked again."""

from __future__ import annotations

import torch

from eofnn.data.history import HISTORY_KINDS, HistorySpec
from eofnn.errors import require
from eofnn.models.linear import LinearFilter

#: The filter structures the analysis knows.
STRUCTURES = ("per_actuator", "shared", "neighbourhood", "modal")
#: Largest filter weight (nm of command per nm of history) the analysis accepts.
MAX_WEIGHT = 1e12


def _values_problem(weights: torch.Tensor) -> str | None:
    """Why ``weights``' values cannot be analysed (non-finite, or too large to be a predictor's), or ``None``."""
    finite = weights[weights.isfinite()]
    if finite.numel() != weights.numel():
        return f"weights hold {weights.numel() - finite.numel()} non-finite value(s): no loop runs them"
    largest = float(finite.abs().max()) if finite.numel() else 0.0
    # A filter weight is nm of command per nm: beyond 1e12 it cannot be a predictor, and the polynomial roots
    # of such weights overflow (reporting "stable, max root 0" for 1e150).
    if largest > MAX_WEIGHT:
        return (f"weights reach {largest:.3g} (nm per nm): at most {MAX_WEIGHT:g} can be analysed; such a filter is "
                "not a predictor")
    return None


def check_weights(weights: torch.Tensor, kind: str, history_length: int, structure: str,
                  neighbours: torch.Tensor | None) -> None:
    """Refuse, in one line, weights that are not a ``structure`` filter of a ``kind`` history of ``history_length``
    frames, or whose values cannot be analysed."""
    require(kind in HISTORY_KINDS, f"history kind={kind!r} is invalid: allowed are {', '.join(HISTORY_KINDS)}")
    require(structure in STRUCTURES, f"structure={structure!r} is invalid: allowed are {', '.join(STRUCTURES)}")
    require(isinstance(history_length, int) and history_length >= 1,
            f"history_length={history_length!r} is invalid: it must be an integer >= 1")
    require(isinstance(weights, torch.Tensor) and weights.dim() == 2,
            f"weights must be a 2-D tensor (groups, taps), got {getattr(weights, 'shape', type(weights).__name__)}")
    taps = history_length * (2 if kind == "closed_loop" else 1)
    shape = tuple(weights.shape)
    problem = _values_problem(weights)
    require(problem is None, problem or "")
    if structure == "neighbourhood":
        require(neighbours is not None and neighbours.dim() == 2 and neighbours.shape[0] == shape[0]
                and shape[1] == neighbours.shape[1] * taps,
                f"neighbourhood weights of shape {shape} do not fit neighbours of shape "
                f"{None if neighbours is None else tuple(neighbours.shape)} and {taps} taps per actuator")
    else:
        require(shape[1] == taps and (structure in ("per_actuator", "modal") or shape[0] == 1),
                f"weights of shape {shape} do not fit structure={structure!r} with {taps} taps per actuator "
                f"({kind}, history_length={history_length}): expected ({'1' if structure == 'shared' else 'K'}, {taps})")


def check_filter(network: LinearFilter, spec: HistorySpec) -> None:
    """Refuse, in one line, what is not a :class:`LinearFilter`, one whose taps are not ``spec``'s, or one whose
    weights' values cannot be analysed (its structure and shape are its own construction's)."""
    require(isinstance(network, LinearFilter), f"stability analysis needs a LinearFilter, got {type(network).__name__}")
    require(network.n_taps == spec.n_taps, f"filter has {network.n_taps} taps but the history spec has {spec.n_taps}")
    problem = _values_problem(network.weight.detach())
    require(problem is None, problem or "")
