"""Actuators anywhere: a layout from positions in metres, neighbourhoods by distance, a shift model on it.

eofnn's simulator uses its own cell-centred square grid (:class:`~eofnn.sim.grid.ActuatorGrid`); telemetry from other
loops comes on their layouts: a subset of a square lattice in either convention (cell-centred, or Fried: ``n + 1``
across at the subaperture corners), a hexagonal one, or anything. :class:`ActuatorLayout` holds such positions and
gives what the telemetry side needs:

- the *pitch*: the median nearest-neighbour distance (metres);
- *neighbourhoods by distance* (:meth:`ActuatorLayout.neighbours`): a KD-tree finds every actuator within
  ``radius`` pitches; on a lattice (few distinct offsets) each column of the index table is one offset, for every
  actuator, in the order of :meth:`ActuatorGrid.neighbours` (squared distance, then ``(dy, dx)``), so on eofnn's own
  grid the two tables are equal; on an irregular layout each row lists its neighbours by distance. Slots beyond the
  layout hold ``K`` (one past the end, read as zero);
- a *shift model* (:meth:`ActuatorLayout.shift_operator`): the applied shape at actuator ``k`` is the commanded
  shape interpolated at ``p_k - shift``: bilinear on a square lattice (as the simulator's misregistration), linear
  on the Delaunay triangles otherwise (what :class:`scipy.interpolate.LinearNDInterpolator` does; points outside
  the layout's hull take the clipped weights of a triangle at the actuator).

:func:`layout_from_dict` rebuilds either kind from the ``grid`` dict that networks and ``plant.json`` store:
``{"diameter_m", "n_across", "obstruction"}`` for eofnn's grid, ``{"positions_m": [[x, y], ...]}`` for a layout.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
import torch

from eofnn.errors import TelemetryError
from eofnn.sim.grid import ActuatorGrid
from eofnn.telemetry.positions import OFFSET_TOLERANCE, check_positions
from eofnn.validation import Interval, check_value

#: Positions within this many pitches of a square lattice point make the layout a square lattice (bilinear shifts).
LATTICE_TOLERANCE = 1e-3


class ActuatorLayout:
    """Actuators at arbitrary ``(K, 2)`` positions (x, y) in metres.

    Parameters
    ----------
    positions_m : array_like
        ``(K, 2)`` actuator (x, y) positions in metres, ``K >= 4``, finite, no two closer than
        ``OFFSET_TOLERANCE`` pitches.
    """

    def __init__(self, positions_m) -> None:
        self.positions_m = check_positions(positions_m)
        self.pitch_m = _median_nearest(self.positions_m)

    @classmethod
    def from_dict(cls, values: dict) -> ActuatorLayout:
        return cls(values["positions_m"])

    def to_dict(self) -> dict:
        """``{"positions_m": [[x, y], ...]}``: what networks and ``plant.json`` store (exact floats)."""
        return {"positions_m": self.positions_m.tolist()}

    @property
    def n_actuators(self) -> int:
        return len(self.positions_m)

    @cached_property
    def _tree(self):
        from scipy.spatial import cKDTree

        return cKDTree(self.positions_m)

    @cached_property
    def lattice_indices(self) -> np.ndarray | None:
        """``(K, 2)`` integer (row, column) on an axis-aligned square lattice of the pitch, or None if not one."""
        u = (self.positions_m - self.positions_m.min(0)) / self.pitch_m
        index = np.round(u)
        if np.abs(u - index).max() > LATTICE_TOLERANCE:
            return None
        return index[:, ::-1].astype(np.int64)

    @property
    def kind(self) -> str:
        """``"square"`` (a subset of a square lattice, either convention: bilinear shifts) or ``"triangulated"``."""
        return "square" if self.lattice_indices is not None else "triangulated"

    def ptt_basis(self) -> np.ndarray:
        """Orthonormal ``(K, 3)`` basis of piston, tip and tilt over the actuators."""
        x, y = self.positions_m.T
        q, _ = np.linalg.qr(np.stack([np.ones_like(x), x, y], axis=1))
        return q

    # -- neighbourhoods ---------------------------------------------------------------------------------------
    def neighbours(self, radius: float) -> torch.Tensor:
        """``(K, M)`` long tensor of the actuators within ``radius`` pitches of each (itself first); slots beyond the
        layout hold ``K``. On a lattice each column is one offset (:attr:`offsets` after a call), else rows list
        neighbours by distance. A layout where some actuator has no neighbour within ``radius >= 1`` is too
        sparse: one-line :class:`TelemetryError`."""
        return torch.as_tensor(self._table(radius)[0])

    def neighbour_offsets(self, radius: float) -> np.ndarray:
        """``(K, M, 2)`` offsets (x, y) in pitches of each slot of :meth:`neighbours` (NaN for empty slots)."""
        table, _ = self._table(radius)
        padded = np.vstack([self.positions_m, np.full((1, 2), np.nan)])
        return (padded[table] - self.positions_m[:, None, :]) / self.pitch_m

    def is_regular(self, radius: float) -> bool:
        """Whether each column of :meth:`neighbours` is one offset for every actuator (a lattice)."""
        return self._table(radius)[1]

    def _table(self, radius: float) -> tuple[np.ndarray, bool]:
        cache = self.__dict__.setdefault("_tables", {})
        if radius not in cache:
            cache[radius] = self._build_table(radius)
        return cache[radius]

    def _build_table(self, radius: float) -> tuple[np.ndarray, bool]:
        check_value("neighbourhood radius", radius, Interval(0, 64, unit="pitches"))
        pos, k = self.positions_m, self.n_actuators
        lists = self._tree.query_ball_point(pos, radius * self.pitch_m * (1 + 1e-9) + 1e-12)
        counts = np.array([len(nb) for nb in lists])
        if radius >= 1 and (counts < 2).any():
            lonely = int(np.argmax(counts < 2))
            nearest = self._tree.query(pos, k=2)[0][:, 1] / self.pitch_m
            raise TelemetryError(
                f"actuator layout too sparse for neighbourhood radius {radius:g} pitches (pitch {self.pitch_m:.4g} m, "
                f"the median nearest-neighbour distance): actuator {lonely} at {pos[lonely].round(4).tolist()} m has no "
                f"neighbour within it (nearest at {nearest[lonely]:.3g} pitches); allowed: radius >= "
                f"{float(nearest.max()):.3g} pitches, or a per-actuator or shared structure")
        rows = np.repeat(np.arange(k), counts)
        cols = np.concatenate([np.asarray(nb, dtype=np.int64) for nb in lists])
        offsets = (pos[cols] - pos[rows]) / self.pitch_m
        labels, centres = _cluster(offsets, limit=4 * int(counts.max()))
        if labels is not None:
            # Columns in the order of ActuatorGrid.neighbours: squared distance, then (dy, dx).
            order = np.lexsort((centres[:, 0].round(6), centres[:, 1].round(6), (centres ** 2).sum(1).round(6)))
            column = np.empty(len(order), dtype=np.int64)
            column[order] = np.arange(len(order))
            table = np.full((k, len(order)), k, dtype=np.int64)
            slots = column[labels]
            if len(np.unique(rows * len(order) + slots)) == len(rows):  # one neighbour per offset and actuator
                table[rows, slots] = cols
                return table, True
        # Irregular: each row by distance (then angle), padded with K.
        table = np.full((k, int(counts.max())), k, dtype=np.int64)
        for i, nb in enumerate(lists):
            nb = np.asarray(nb, dtype=np.int64)
            d = pos[nb] - pos[i]
            table[i, : len(nb)] = nb[np.lexsort((np.arctan2(d[:, 1], d[:, 0]).round(9), np.hypot(*d.T).round(12)))]
        return table, False

    # -- shift model ------------------------------------------------------------------------------------------
    def shift_operator(self, dx: float, dy: float) -> tuple[torch.Tensor, torch.Tensor]:
        """``(index, weight)``, each ``(K, 3 or 4)``: the applied shape at ``k`` is ``sum_m weight[k, m] *
        y[index[k, m]]``, the commanded shape interpolated at ``p_k - (dx, dy) * pitch`` (``index == K`` reads
        zero). Bilinear on a square lattice, linear on Delaunay triangles otherwise (outside the hull: a triangle at
        the actuator, weights clipped to >= 0 and renormalised)."""
        if self.lattice_indices is not None:
            return _bilinear(self.lattice_indices, dx, dy)
        tri = self._delaunay
        query = self.positions_m - np.array([dx, dy]) * self.pitch_m
        found = tri.find_simplex(query)
        # Outside the hull: a triangle at the actuator itself, weights clipped to >= 0 and renormalised (the
        # identity at zero shift; no extrapolation, which thin hull triangles would blow up).
        simplex = np.where(found >= 0, found, tri.vertex_to_simplex)
        transform = tri.transform[simplex]
        bary = np.einsum("kij,kj->ki", transform[:, :2], query - transform[:, 2])
        weight = np.concatenate([bary, 1 - bary.sum(1, keepdims=True)], 1)
        clipped = weight.clip(min=0)
        weight = np.where((found >= 0)[:, None], weight, clipped / clipped.sum(1, keepdims=True))
        return torch.as_tensor(tri.simplices[simplex].astype(np.int64)), torch.as_tensor(weight)

    @cached_property
    def _delaunay(self):
        from scipy.spatial import Delaunay

        return Delaunay(self.positions_m)

    def stencil_inside(self, radius: float) -> np.ndarray:
        """``(K,)`` bool: actuators whose shift-model stencil (the 3 x 3 lattice block, or their Delaunay
        triangles that hold the points a quarter and half a pitch away in 8 directions, for shifts up to half a pitch) lies inside
        the layout and within ``radius`` pitches."""
        pos, tol = self.positions_m, 1 + 1e-9
        if self.lattice_indices is not None:
            count = np.array([len(nb) for nb in self._tree.query_ball_point(pos, 1.5 * self.pitch_m)])
            return (count == 9) & (radius * tol >= np.sqrt(2))
        tri = self._delaunay
        angles = np.arange(8) * np.pi / 4
        ring = np.stack([np.cos(angles), np.sin(angles)], 1)
        probes = pos[:, None, :] + self.pitch_m * np.concatenate([0.25 * ring, 0.5 * ring])[None]
        simplex = tri.find_simplex(probes.reshape(-1, 2)).reshape(len(pos), 16)
        stencil = np.where(simplex[..., None] >= 0, tri.simplices[simplex], -1).reshape(len(pos), -1)
        distance = np.hypot(*(pos[stencil] - pos[:, None, :]).transpose(2, 0, 1))
        return (simplex >= 0).all(1) & (distance <= radius * self.pitch_m * tol).all(1)

    def shift_model_note(self) -> str:
        """How :meth:`shift_operator` interpolates, for logs and ``plant.json``."""
        if self.lattice_indices is not None:
            return "bilinear interpolation of the commands on the square lattice"
        return "linear interpolation of the commands on the Delaunay triangles of the positions"


def layout_from_dict(values: dict) -> ActuatorGrid | ActuatorLayout:
    """eofnn's grid from ``{"diameter_m", "n_across", "obstruction"[, "active_diameter_m"]}``, a layout from
    ``{"positions_m": ...}``."""
    if "positions_m" in values:
        return ActuatorLayout.from_dict(values)
    return ActuatorGrid(**values)


def layout_to_dict(layout: ActuatorGrid | ActuatorLayout) -> dict:
    """The dict :func:`layout_from_dict` reads back."""
    if isinstance(layout, ActuatorGrid):
        out = {"diameter_m": layout.diameter_m, "n_across": layout.n_across, "obstruction": layout.obstruction}
        return out if layout.active_diameter_m is None else {**out, "active_diameter_m": layout.active_diameter_m}
    return layout.to_dict()


def layout_from_positions(positions_m) -> ActuatorGrid | ActuatorLayout:
    """eofnn's own grid when the positions are one (same tables and numbers as before), else a layout."""
    layout = ActuatorLayout(positions_m)
    if layout.lattice_indices is None:  # not even a square lattice: not eofnn's grid
        return layout
    try:
        return ActuatorGrid.from_positions(layout.positions_m)
    except TelemetryError:
        return layout


def _median_nearest(pos: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    return float(np.median(cKDTree(pos).query(pos, k=2)[0][:, 1]))


def _cluster(offsets: np.ndarray, limit: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Labels and centres of the distinct offsets (within ``OFFSET_TOLERANCE``); ``(None, None)`` past ``limit``."""
    from scipy.spatial import cKDTree

    keys, inverse = np.unique(np.round(offsets / (OFFSET_TOLERANCE / 4)), axis=0, return_inverse=True)
    if len(keys) > 8 * limit:
        return None, None
    reps = np.stack([np.bincount(inverse.ravel(), weights=offsets[:, i]) for i in range(2)], 1)
    reps /= np.bincount(inverse.ravel())[:, None]
    tree, label = cKDTree(reps), np.full(len(reps), -1)
    centres = []
    for i in range(len(reps)):
        if label[i] >= 0:
            continue
        members = [m for m in tree.query_ball_point(reps[i], OFFSET_TOLERANCE) if label[m] < 0]
        label[members] = len(centres)
        centres.append(reps[members].mean(0))
        if len(centres) > limit:
            return None, None
    return label[inverse.ravel()], np.array(centres)


def _bilinear(indices: np.ndarray, dx: float, dy: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear shift by ``(dx, dy)`` pitches on lattice ``(row, column)`` indices, as the simulator's
    :func:`eofnn.sim.loop.plant._shift_operator` (lattice points without an actuator read zero)."""
    k = len(indices)
    shape = indices.max(0) + 1
    lookup = np.full(tuple(shape), k, dtype=np.int64)
    lookup[indices[:, 0], indices[:, 1]] = np.arange(k)
    src_r, src_c = indices[:, 0] - dy, indices[:, 1] - dx
    r0, c0 = np.floor(src_r).astype(int), np.floor(src_c).astype(int)
    fr, fc = src_r - r0, src_c - c0
    index, weight = [], []
    for ddr, ddc, w in ((0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc), (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
        rr, cc = r0 + ddr, c0 + ddc
        ok = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
        index.append(np.where(ok, lookup[np.clip(rr, 0, shape[0] - 1), np.clip(cc, 0, shape[1] - 1)], k))
        weight.append(np.where(ok, w, 0.0))
    return torch.as_tensor(np.stack(index, 1)), torch.as_tensor(np.stack(weight, 1))


def dm_model(layout: ActuatorGrid | ActuatorLayout | None, dm_gain: float, misregistration_x: float = 0.0,
             misregistration_y: float = 0.0):
    """``y -> DM(y)`` (nm) of a linear DM with gain and misregistration (pitches) on ``layout``: the simulator's
    bilinear shift on eofnn's grid, :meth:`ActuatorLayout.shift_operator` on a layout; a misregistration without a
    layout is a one-line :class:`TelemetryError`."""
    gain = float(dm_gain)
    if not (misregistration_x or misregistration_y):
        return lambda y: gain * y
    if layout is None:
        raise TelemetryError("a misregistered DM model needs the actuator grid: put positions_m in the telemetry")
    if isinstance(layout, ActuatorGrid):
        from eofnn.sim.loop.plant import Plant, PlantModel

        return PlantModel(Plant().with_errors(dm_gain=gain, misregistration_x=misregistration_x,
                                              misregistration_y=misregistration_y), layout).apply_dm
    operator = layout.shift_operator(misregistration_x, misregistration_y)
    return lambda y: gain * apply_shift(y, operator)


def apply_shift(y: torch.Tensor, operator: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """``(..., K)`` commands through a :meth:`ActuatorLayout.shift_operator` ``(index, weight)``."""
    index, weight = operator
    padded = torch.cat([y, torch.zeros_like(y[..., :1])], dim=-1)
    return (padded[..., index] * weight.to(y.dtype)).sum(-1)


def coupling_stencils(grid: ActuatorGrid | ActuatorLayout | None, neighbours: torch.Tensor, radius: float,
                      modal: bool = False) -> tuple[torch.Tensor, torch.Tensor, str]:
    """For plant identification (:mod:`eofnn.training.identify`) over the ``neighbours`` table of ``grid``:
    offsets (row, column) = (y, x) in pitches of the coupling slots (``(M, 2)`` on a lattice, ``(K, M, 2)``
    otherwise, 0 in empty slots), which actuators have the whole stencil of the layout's shift model within their
    neighbourhood (the misregistration is pooled over them), and, if none has, one line saying why it is skipped."""
    n_act, n_nb = neighbours.shape
    if grid is None:
        why = ("the telemetry is modal (y and wfs are coefficients of its modal_basis), so the DM gain is each "
               "mode's response to its own dither" if modal else "the telemetry has no actuator positions "
               "(POSITIONS), so the DM gain is each actuator's response to its own dither")
        return (torch.zeros(1, 2, dtype=torch.float64), torch.zeros(n_act, dtype=torch.bool),
                f"misregistration not identified: no shift model exists ({why}; a misregistration would lower it)")
    complete = (neighbours < n_act).all(1)
    if isinstance(grid, ActuatorGrid):
        k0 = int(complete.nonzero()[0]) if complete.any() else 0
        indices = torch.as_tensor(grid.indices)
        offsets = (indices[neighbours[k0]] - indices[k0]).to(torch.float64)
        interior = complete
    else:
        per_actuator = torch.as_tensor(grid.neighbour_offsets(radius)[..., ::-1].copy()).nan_to_num(0.0)
        interior = torch.as_tensor(grid.stencil_inside(radius))
        offsets = per_actuator[int(complete.nonzero()[0])] if grid.is_regular(radius) and complete.any() \
            else per_actuator
        if offsets.ndim == 2:
            interior = interior & complete
    if interior.any():
        return offsets, interior, ""
    return (offsets, interior, f"misregistration not identified: no actuator has the stencil of the shift model "
            f"within radius {radius:g} pitches (the layout is too small or too sparse for a shift model); the DM "
            "gain is pooled over all actuators")
