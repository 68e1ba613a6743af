"""Actuator positions as telemetry carries them: a ``(K, 2)`` array of (x, y) in metres, checked once on reading."""

from __future__ import annotations

import numpy as np

from eofnn.errors import TelemetryError
from eofnn.lazy import lazy_module

torch = lazy_module("torch")

#: Offsets closer than this (pitches) are the same lattice offset; positions closer than it are duplicates.
OFFSET_TOLERANCE = 0.05


def check_positions(positions_m, n_actuators: int | None = None) -> np.ndarray:
    """``(K, 2)`` float64 positions in metres, or one :class:`TelemetryError` line naming what is wrong."""
    if isinstance(positions_m, torch.Tensor):
        positions_m = positions_m.detach().cpu().numpy()
    pos = np.asarray(positions_m)
    if pos.dtype.kind not in "fiu":
        raise TelemetryError(f"actuator positions have dtype {pos.dtype}: they must be real numbers (metres)")
    pos = pos.astype(np.float64)
    want = "actuators" if n_actuators is None else n_actuators
    if pos.ndim != 2 or pos.shape[1] != 2 or len(pos) < 4 or (n_actuators is not None and len(pos) != n_actuators):
        raise TelemetryError(f"actuator positions have shape {pos.shape}: expected ({want}, 2) actuator (x, y) in "
                             "metres, at least 4 actuators, one row per column of the arrays")
    bad = ~np.isfinite(pos).all(1)
    if bad.any():
        raise TelemetryError(f"actuator positions hold {int(bad.sum())} non-finite row(s) (NaN or inf), first at row "
                             f"{int(np.argmax(bad))}: every position must be a finite (x, y) in metres")
    from scipy.spatial import cKDTree

    tree = cKDTree(pos)
    pitch = float(np.median(tree.query(pos, k=2)[0][:, 1]))
    pairs = tree.query_pairs(OFFSET_TOLERANCE * pitch, output_type="ndarray")
    if len(pairs) or pitch == 0:
        i, j = sorted(pairs[np.lexsort(pairs.T[::-1])][0].tolist()) if len(pairs) else (0, 1)
        raise TelemetryError(f"actuator positions hold duplicates: rows {i} and {j} are "
                             f"{np.hypot(*(pos[i] - pos[j])):.3g} m apart at {pos[i].round(6).tolist()} m; allowed: "
                             f"distinct positions, more than {OFFSET_TOLERANCE} pitch ({pitch:.4g} m) apart")
    return pos
