"""Subaperture helpers of :mod:`eofnn.sim.sensing.shack_hartmann`: the edge quadrature, the actuator lattice, and
partly lit subapertures (which fraction of each is inside the pupil, and the slopes of one that is partly lit).

A Shack-Hartmann lenslet that the pupil's rim cuts forms the spot of its lit area alone; its centroid is that area's
mean phase gradient (the centroid theorem; with a diffractive spot the same, truncation of its wings aside).
:class:`~eofnn.sim.sensing.shack_hartmann.SubapertureGeometry` keeps its edge-difference slopes (Gauss's theorem,
Simpson's rule along the edges) for a fully lit subaperture and uses :func:`partly_lit_rows` for the others: the
mean over the subaperture's fine cells of each cell's difference across it, weighted by the cell's lit fraction.
Exact for a tilt (``tests/test_shack_hartmann.py``); fully lit it would be the trapezoid rule on the edges.
"""

from __future__ import annotations

import numpy as np

from eofnn.sim.grid import ActuatorGrid


def _in_pupil(x: np.ndarray, y: np.ndarray, pupil_m: float, obstruction_m: float) -> np.ndarray:
    r = np.hypot(x, y)
    return (r <= pupil_m / 2) & (r >= obstruction_m / 2)


def lit_fractions(centres: np.ndarray, side: float, pupil_m: float, obstruction_m: float, samples: int) -> np.ndarray:
    """Fraction of each ``side`` x ``side`` square centred on ``centres`` ``(n, 2)`` inside the (obstructed) pupil,
    on a ``samples`` x ``samples`` grid of sub-cell centres."""
    u = ((np.arange(samples) + 0.5) / samples - 0.5) * side
    dy, dx = (a.ravel() for a in np.meshgrid(u, u, indexing="ij"))
    return np.array([_in_pupil(cx + dx, cy + dy, pupil_m, obstruction_m).mean() for cx, cy in centres])


def partly_lit_rows(partial, row0, col0, m: int, h: float, n_valid: int, lookup, pupil_m: float,
                     obstruction_m: float):
    """``(rows, columns, values)`` of the x and y slopes of the ``partial`` subapertures: ``m`` times the lit area's
    mean of each fine cell's difference across it (the mean of its two edges' differences), cells weighted by their
    lit fraction (16 x 16 samples each). Fully lit, this is the trapezoid rule on the edges."""
    out_r, out_c, out_v = [], [], []
    cells = np.arange(m)
    cr, cc = (a.ravel() for a in np.meshgrid(cells, cells, indexing="ij"))  # cell (row, col) in the subaperture
    for sub in partial:
        r0, c0 = row0[sub], col0[sub]
        # Cell centres in metres: the fine grid's point (i, j) is at (j h, i h) from its corner point (0, 0) at
        # -(n_fine - 1) h / 2.
        n_fine = lookup.shape[0]
        x = (c0 + cc + 0.5 - (n_fine - 1) / 2) * h
        y = (r0 + cr + 0.5 - (n_fine - 1) / 2) * h
        weight = lit_fractions(np.stack([x, y], 1), h, pupil_m, obstruction_m, 16)
        weight = weight / weight.sum()
        for axis in (0, 1):
            rows_, cols_, vals_ = [], [], []
            for (dr0, dc0, dr1, dc1) in ((0, 0, 0, 1), (1, 0, 1, 1)) if axis == 0 else ((0, 0, 1, 0), (0, 1, 1, 1)):
                # difference along the axis on one of the cell's two edges, half weight each
                for sign, dr, dc in ((1.0, dr1, dc1), (-1.0, dr0, dc0)):
                    idx = lookup[r0 + cr + dr, c0 + cc + dc]
                    if (idx < 0).any():
                        raise AssertionError("a subaperture cell corner lies outside the fine grid")
                    rows_.append(np.full(m * m, axis * n_valid + sub))
                    cols_.append(idx)
                    vals_.append(sign * 0.5 * m * weight)
            out_r += rows_
            out_c += cols_
            out_v += vals_
    return tuple(np.concatenate(a) for a in (out_r, out_c, out_v))


def edge_weights(m: int) -> np.ndarray:
    """Weights of the mean over ``m + 1`` equally spaced points of an edge (summing to 1): Simpson's rule for even
    ``m``, the trapezoid rule for odd ``m``."""
    if m % 2 == 0:
        w = np.ones(m + 1)
        w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    else:
        w = np.full(m + 1, 2.0)
        w[0] = w[-1] = 1.0
    return w / w.sum()


def lattice(grid: ActuatorGrid) -> np.ndarray:
    """``(n_across², 2)`` (x, y) of every site of ``grid``'s square lattice, active or not (m), row-major."""
    centres = (np.arange(grid.n_across) + 0.5) * grid.pitch_m - grid.diameter_m / 2
    yy, xx = np.meshgrid(centres, centres, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1)
