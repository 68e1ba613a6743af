"""The deformable-mirror actuator grid of a circular (optionally obstructed) pupil."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar

import numpy as np

from eofnn.errors import ConfigError, TelemetryError
from eofnn.lazy import lazy_module
from eofnn.resources import require_memory
from eofnn.validation import Constraint, Interval, check_value, validated

torch = lazy_module("torch")

#: Largest grid accepted: 512 x 512 actuators already needs ~1.6 GB per 1000 float64 frames of telemetry.
MAX_N_ACROSS = 512


@dataclass(frozen=True)
@validated
class ActuatorGrid:
    """Actuators on a square grid of ``n_across`` x ``n_across`` at pitch ``diameter_m / n_across``.

    Actuator centres lie at ``(i + 0.5) * pitch - diameter_m / 2``; those inside the pupil (radius
    ``diameter_m / 2``, outside the central obstruction of fractional diameter ``obstruction``) are active, or with
    ``active_diameter_m`` those within ``active_diameter_m / 2`` of the centre (a DM whose actuators end elsewhere
    than its lattice's pupil: OOPAO's Fried DM keeps those within ``D / 2 + 0.7533 pitch`` of a pupil ``D`` that ends
    half a pitch inside its last row; a Shack-Hartmann's ``pupil_diameter_m`` sets the lit pupil).

    Parameters
    ----------
    diameter_m : float
        Telescope diameter in metres.
    n_across : int
        Actuators across the pupil diameter.
    obstruction : float
        Central obstruction as a fraction of the diameter, in [0, 0.9].
    active_diameter_m : float or None
        Actuators whose centres lie within half of it from the centre are active (m); ``None``: ``diameter_m``. At
        most ``diameter_m * sqrt(2)`` (the lattice's corners).
    """

    diameter_m: float = 8.0
    n_across: int = 40
    obstruction: float = 0.0
    active_diameter_m: float | None = None

    _constraints: ClassVar[dict[str, Constraint]] = {
        "diameter_m": Interval(0, 100, closed="right", unit="m"),
        "n_across": Interval(2, MAX_N_ACROSS, integer=True, unit="actuators across the pupil"),
        "obstruction": Interval(0, 0.9, unit="fraction of the diameter"),
    }

    def __post_init__(self) -> None:
        if self.active_diameter_m is not None:
            check_value("active_diameter_m", self.active_diameter_m,
                        Interval(0, self.diameter_m * 2 ** 0.5, closed="right", unit=f"m (the lattice is "
                                 f"{self.diameter_m:g} m across)"))
        # Counted without filling the cached properties: a config object's __dict__ stays its fields.
        active = int(_pupil_mask(_square_grid(self.diameter_m, self.n_across), self.diameter_m, self.n_across,
                                 self.obstruction, self.active_diameter_m).sum())
        if active < 4:  # piston, tip and tilt need three actuators, a predictor one more
            raise ConfigError(f"obstruction={self.obstruction!r}, active_diameter_m={self.active_diameter_m!r} with "
                              f"n_across={self.n_across} leave {active} active actuators: at least 4 are needed")

    @classmethod
    def from_positions(cls, positions_m, tolerance: float = 1e-3) -> ActuatorGrid:
        """The grid whose active actuators are ``positions_m`` ``(K, 2)`` (metres), listed in this class's order.

        The pitch is the smallest spacing, the grid is centred on the positions' bounding box, and the central
        obstruction (if any) is the innermost radius; a layout that is not such a grid, or that lists the actuators
        in another order, raises :class:`~eofnn.errors.TelemetryError` (``tolerance`` in pitches).
        """
        pos = np.asarray(positions_m, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 2 or len(pos) < 4:
            raise TelemetryError(f"actuator positions have shape {pos.shape}: expected (actuators >= 4, 2) in metres")
        if not np.isfinite(pos).all():
            raise TelemetryError("actuator positions hold non-finite values (NaN or inf)")
        from scipy.spatial import cKDTree

        # The smallest Chebyshev spacing, by KD-tree: a (K, K) table of gaps would need gigabytes for an ELT's DM.
        gaps = cKDTree(pos).query(pos, k=min(len(pos), 3), p=np.inf)[0][:, 1:]
        if gaps.size == 0 or not (gaps > 0).all():
            same = int((gaps == 0).any(1).sum()) if gaps.size else len(pos)
            where = "all lie at one point" if gaps.size == 0 or not (gaps > 0).any() else f"repeat ({same} share a place)"
            raise TelemetryError(f"actuator positions ({len(pos)} actuators) {where}: each actuator needs a place of "
                                 "its own on the grid")
        pitch = float(gaps.min())
        centre = (pos.max(0) + pos.min(0)) / 2
        n_across = int(round(float((pos.max(0) - pos.min(0)).max()) / pitch)) + 1
        radius = np.hypot(*(pos - centre).T)
        obstruction = float(radius.min() / (n_across * pitch / 2)) if radius.min() > pitch else 0.0
        # Rounded to 12 digits: positions written in metres give back the diameter they were made from.
        grid = cls(float(f"{n_across * pitch:.12g}"), n_across, max(0.0, float(f"{obstruction:.12g}") - 1e-9))
        if grid.n_actuators != len(pos) or np.abs(grid.positions_m - (pos - centre)).max() > tolerance * pitch:
            raise TelemetryError(f"actuator positions ({len(pos)} actuators, pitch {pitch:.4g} m) are not the active "
                                 "actuators of a square grid on a circular pupil in row-major order (y then x): "
                                 "neighbourhoods cannot be built from them")
        return grid

    @property
    def pitch_m(self) -> float:
        """Actuator pitch in metres."""
        return self.diameter_m / self.n_across

    @cached_property
    def _full_coords(self) -> np.ndarray:
        return _square_grid(self.diameter_m, self.n_across)

    @cached_property
    def mask(self) -> np.ndarray:
        """Boolean ``(n_across, n_across)`` map of active actuators (row = y, column = x)."""
        return _pupil_mask(self._full_coords, self.diameter_m, self.n_across, self.obstruction, self.active_diameter_m)

    @property
    def n_actuators(self) -> int:
        """Number of active actuators."""
        return int(self.mask.sum())

    @cached_property
    def positions_m(self) -> np.ndarray:
        """``(n_actuators, 2)`` array of active actuator (x, y) positions in metres."""
        return self._full_coords[self.mask.ravel()]

    @cached_property
    def indices(self) -> np.ndarray:
        """``(n_actuators, 2)`` integer (row, column) of each active actuator on the square grid."""
        rows, cols = np.nonzero(self.mask)
        return np.stack([rows, cols], axis=1)

    def ptt_basis(self) -> np.ndarray:
        """Orthonormal ``(n_actuators, 3)`` basis of piston, tip and tilt over the active actuators."""
        x, y = self.positions_m.T
        modes = np.stack([np.ones_like(x), x, y], axis=1)
        q, _ = np.linalg.qr(modes)
        return q

    def neighbours(self, radius: float) -> torch.Tensor:
        """Indices of the active actuators within ``radius`` pitches of each actuator.

        Returns a ``(n_actuators, n_neighbours)`` long tensor; the first column is the actuator itself and
        slots beyond the pupil edge hold ``n_actuators`` (an index one past the end, for a zero pad).
        Offsets are in a fixed order, so the same offset has the same column for every actuator.
        """
        check_value("neighbourhood radius", radius, Interval(0, self.n_across, unit="pitches"))
        r = int(np.floor(radius))
        # Count before building: the table is n_actuators x (about pi r^2) indices, and the filter's weights and
        # gathered histories are that times the taps.
        n_offsets = sum(2 * int(np.floor(np.sqrt(max(radius * radius + 1e-9 - dr * dr, 0.0)))) + 1
                        for dr in range(-r, r + 1))
        require_memory(8.0 * self.n_actuators * n_offsets * 4, f"a neighbourhood of radius {radius:g} pitches "
                       f"({n_offsets} actuators each) on {self.n_actuators} actuators")
        offsets = [
            (dr, dc)
            for dr in range(-r, r + 1)
            for dc in range(-r, r + 1)
            if dr * dr + dc * dc <= radius * radius + 1e-9
        ]
        offsets.sort(key=lambda o: (o[0] ** 2 + o[1] ** 2, o))
        lookup = np.full((self.n_across, self.n_across), self.n_actuators, dtype=np.int64)
        lookup[self.mask] = np.arange(self.n_actuators)
        padded = np.pad(lookup, r, constant_values=self.n_actuators)
        rows, cols = self.indices.T
        columns = [padded[rows + r + dr, cols + r + dc] for dr, dc in offsets]
        return torch.as_tensor(np.stack(columns, axis=1))

    def to_map(self, values: torch.Tensor, fill: float = float("nan")) -> torch.Tensor:
        """Scatter ``(..., n_actuators)`` values onto ``(..., n_across, n_across)`` maps."""
        out = torch.full((*values.shape[:-1], self.n_across * self.n_across), fill, dtype=values.dtype)
        out[..., torch.as_tensor(np.flatnonzero(self.mask.ravel()))] = values
        return out.reshape(*values.shape[:-1], self.n_across, self.n_across)


def _square_grid(diameter_m: float, n_across: int) -> np.ndarray:
    """``(n_across**2, 2)`` (x, y) centres of the square actuator grid, in metres."""
    pitch = diameter_m / n_across
    centres = (np.arange(n_across) + 0.5) * pitch - diameter_m / 2
    yy, xx = np.meshgrid(centres, centres, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


def _pupil_mask(coords: np.ndarray, diameter_m: float, n_across: int, obstruction: float,
                active_diameter_m: float | None = None) -> np.ndarray:
    """Which grid centres lie in the (obstructed) pupil, or within ``active_diameter_m / 2`` of the centre, as an
    ``(n_across, n_across)`` boolean map."""
    r = np.hypot(coords[:, 0], coords[:, 1])
    # A small tolerance keeps actuators that sit exactly on the rim, whatever the rounding.
    tol = 1e-9 * diameter_m
    outer = diameter_m if active_diameter_m is None else active_diameter_m
    inside = (r <= outer / 2 + tol) & (r >= obstruction * diameter_m / 2 - tol)
    return inside.reshape(n_across, n_across)


def grid_reaching(positions_m, diameter_m: float, n_across: int, obstruction: float = 0.0,
                  tolerance: float = 1e-3) -> ActuatorGrid | None:
    """The grid of ``n_across`` actuators across ``diameter_m`` whose active actuators are ``positions_m``
    ``(K, 2)`` (m, in this class's order) with an ``active_diameter_m`` (a DM that reaches past the lattice's
    inscribed circle, as OOPAO's Fried DM does): the active diameter halfway between the farthest position from the
    centre and the next lattice radius out; ``None`` when no such grid lists the positions."""
    pos = np.asarray(positions_m, dtype=np.float64)
    centre = (pos.max(0) + pos.min(0)) / 2
    reach = float(np.hypot(*(pos - centre).T).max())
    radii = np.hypot(*_square_grid(diameter_m, n_across).T)
    beyond = radii[radii > reach + 1e-6 * diameter_m]
    active = float(f"{reach + (beyond.min() if beyond.size else reach + diameter_m / n_across):.6g}")
    if active > diameter_m * 2 ** 0.5:
        return None
    grid = ActuatorGrid(diameter_m, n_across, obstruction, active_diameter_m=active)
    if grid.n_actuators != len(pos) or np.abs(grid.positions_m - (pos - centre)).max() > tolerance * grid.pitch_m:
        return None
    return grid


def nearest_grid(positions_m, pitch_m: float) -> tuple[dict, bool]:
    """The fields of eofnn's grid nearest to actuators at ``positions_m`` ``(K, 2)`` (m) on a square lattice of pitch
    ``pitch_m`` that :meth:`ActuatorGrid.from_positions` does not recognise: the lattice's extent and pitch, the
    central obstruction from the innermost radius and, where one lists exactly these actuators in this class's order
    (:func:`grid_reaching`: a DM that reaches past the lattice's inscribed circle), its active diameter; ``(fields,
    whether the grid's actuators are the positions)``."""
    positions = np.asarray(positions_m, dtype=np.float64)
    radius = np.linalg.norm(positions - positions.mean(0), axis=1)
    n_across = int(round(np.ptp(positions, axis=0).max() / pitch_m)) + 1
    inner = float(radius.min()) - pitch_m / 2
    obstruction = round(max(0.0, inner) / (n_across * pitch_m / 2), 3) if inner > pitch_m else 0.0
    grid = {"diameter_m": round(n_across * pitch_m, 6), "n_across": n_across, "obstruction": obstruction}
    reaching = grid_reaching(positions, grid["diameter_m"], n_across, obstruction)
    if reaching is not None:
        grid["active_diameter_m"] = reaching.active_diameter_m
    return grid, reaching is not None
