"""The DM's Gaussian influence functions at a sensor's fine points, and the truncated least-squares reconstructor
of an interaction matrix (:mod:`eofnn.sim.sensing.shack_hartmann` builds ``D = S IF`` from them)."""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp

from eofnn.errors import ConfigError
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.sensing.constants import MECHANICAL_COUPLING

#: Influence functions are cut where they fall below this fraction of their peak (a radius of
#: ``d sqrt(ln(1e-6) / ln(coupling))``: 3.6 pitches at coupling 0.35).
INFLUENCE_FLOOR = 1e-6

def default_relative_cut(subapertures_across: int) -> float:
    """The reconstructor's default relative singular-value cut: ``min(0.1, 3 / subapertures_across)`` (0.075 at 40
    across; 0.1 up to 30)."""
    return min(0.1, 3.0 / subapertures_across)


def surface_per_command(mechanical_coupling: float = MECHANICAL_COUPLING) -> float:
    """nm of smooth DM surface per nm of command of peak-1 Gaussian influence functions on a square lattice: their
    lattice sum ``(sum_j coupling^(j²))²`` (2.99 at OOPAO's 0.35). eofnn's commands are divided by it (nm of surface
    for a smooth shape, :class:`eofnn.sim.sensing.pupil.PupilOperators`); OOPAO's are not (nm of peak)."""
    j = np.arange(-12, 13)
    return float((mechanical_coupling ** (j * j)).sum() ** 2)


def influence_functions(grid: ActuatorGrid, points_m: np.ndarray,
                        mechanical_coupling: float = MECHANICAL_COUPLING) -> sp.csr_matrix:
    """Gaussian influence functions of ``grid``'s actuators at ``points_m``: a sparse ``(n_points, K)`` matrix.

    ``IF[p, k] = exp(-|x_p - a_k|² / (2 c²))`` with ``c = d / sqrt(2 ln(1 / coupling))`` (``d`` = pitch, m), i.e.
    ``coupling ** (|x_p - a_k|² / d²)``: 1 nm of surface at the actuator per nm of command, ``coupling`` at a
    neighbour (OOPAO's shape, ``DeformableMirror.modesComputation``; OOPAO's default coupling 0.35). Values below
    :data:`INFLUENCE_FLOOR` are dropped. ``mechanical_coupling`` is in (0, 1), as the sensor's config has checked it.
    """
    from scipy.spatial import cKDTree

    d = grid.pitch_m
    radius = d * math.sqrt(math.log(INFLUENCE_FLOOR) / math.log(mechanical_coupling))
    points = np.asarray(points_m, dtype=np.float64)
    near = cKDTree(points).query_ball_point(grid.positions_m, radius)
    cols = np.concatenate([np.full(len(p), k) for k, p in enumerate(near)])
    rows = np.concatenate([np.asarray(p, dtype=np.int64) for p in near])
    r2 = ((points[rows] - grid.positions_m[cols]) ** 2).sum(1) / (d * d)
    return sp.csr_matrix((mechanical_coupling ** r2, (rows, cols)), shape=(len(points), grid.n_actuators))


def least_squares_reconstructor(interaction_matrix: np.ndarray, relative_cut: float
                                ) -> tuple[np.ndarray, int, np.ndarray]:
    """``(R, kept, singular_values)``: the truncated-SVD least-squares reconstructor of ``D``.

    ``D = U Σ V^T``; ``R = V_k Σ_k^-1 U_k^T`` over the ``kept`` singular values above ``relative_cut`` x the largest,
    so ``R D`` is the projector on the kept command modes. ``relative_cut`` is in [0.001, 1], as the sensor's config
    has checked it (or :func:`default_relative_cut`); a cut that keeps nothing is one :class:`ConfigError` line.
    """
    d = np.asarray(interaction_matrix, dtype=np.float64)
    # D^T D = V Σ² V^T (a K x K eigenproblem, several times faster than the SVD of D); the cut is at least 1e-3
    # of the largest singular value, far above the rounding the squaring brings (1e-8 of it).
    eigenvalues, v = np.linalg.eigh(d.T @ d)
    order = np.argsort(eigenvalues)[::-1]
    s = np.sqrt(np.clip(eigenvalues[order], 0.0, None))
    v = v[:, order]
    kept = int((s > relative_cut * s.max()).sum()) if s.size and s.max() > 0 else 0
    if kept == 0:
        raise ConfigError(f"relative_cut={relative_cut!r} removes every mode of the interaction matrix "
                          f"{d.shape} (largest singular value {s.max() if s.size else 0:.3g}): "
                          "allowed a cut below 1 of a matrix that sees something")
    return (v[:, :kept] / s[:kept] ** 2) @ v[:, :kept].T @ d.T, kept, s
