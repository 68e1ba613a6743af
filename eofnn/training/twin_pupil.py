"""The twin's pupil from the system's own matrices (:func:`eofnn.training.twin.identify_twin`, its step 1): the
actuators an interaction matrix sees, the slopes that respond (the valid subapertures), the reconstructor's shape."""

from __future__ import annotations

import numpy as np

from eofnn.errors import TelemetryError

#: An interaction-matrix column (row) below this fraction of the median column (row) norm moves (answers) nothing.
DEAD_FRACTION = 1e-3


def pupil_from_matrices(n_actuators: int, n_slopes: int | None, interaction_matrix=None, reconstructor=None,
                        positions_m=None) -> dict:
    """The actuators the interaction matrix sees and the slopes that respond, the reconstructor's shape checked.

    Returns ``{"valid_slopes": int or None, "valid_subapertures": int or None, "dead_slopes": list}``.

    Raises
    ------
    TelemetryError
        A reconstructor that is not ``(K, S)``; an interaction matrix that is not ``(S, K)``; an actuator of the
        telemetry (a column of ``y``) whose interaction-matrix column is about zero (the telemetry's mask and the
        matrix disagree).
    """
    out: dict = {"valid_slopes": None, "valid_subapertures": None, "dead_slopes": []}
    im = None if interaction_matrix is None else np.asarray(interaction_matrix, dtype=np.float64)
    if im is not None and n_slopes is None:
        n_slopes = im.shape[0]
    if reconstructor is not None:
        r = np.asarray(reconstructor)
        s = n_slopes if n_slopes is not None else (r.shape[1] if r.ndim == 2 else None)
        if r.ndim != 2 or r.shape[0] != n_actuators or s is None or r.shape[1] != s or s % 2:
            expected = f"({n_actuators}, 2 n_sub) = ({n_actuators}, {s})" if s else f"({n_actuators}, 2 n_sub)"
            raise TelemetryError(f"reconstructor has shape {r.shape}: expected {expected}, wfs = R @ slopes for "
                                 f"{n_actuators} actuators and x then y slopes of n_sub subapertures")
    if im is None:
        return out
    if im.ndim != 2 or im.shape != (n_slopes, n_actuators):
        raise TelemetryError(f"interaction_matrix has shape {im.shape}: expected ({n_slopes}, {n_actuators}) "
                             "(slopes = IM @ y)")
    columns = np.linalg.norm(im, axis=0)
    dead = np.flatnonzero(columns < DEAD_FRACTION * np.median(columns))
    if dead.size:
        where = "" if positions_m is None else f" at ({positions_m[dead[0]][0]:.3g}, {positions_m[dead[0]][1]:.3g}) m"
        raise TelemetryError(f"the telemetry's actuators and its interaction matrix disagree: {dead.size} actuator(s) "
                             f"(first: column {int(dead[0])}{where}) move no slope (IM column about 0): drop them from "
                             "y, wfs and positions, or give the interaction matrix of this loop")
    rows = np.linalg.norm(im, axis=1)
    valid = rows >= DEAD_FRACTION * np.median(rows)
    out.update(valid_slopes=int(valid.sum()), valid_subapertures=int(valid.sum()) // 2,
               dead_slopes=np.flatnonzero(~valid).tolist())
    return out
