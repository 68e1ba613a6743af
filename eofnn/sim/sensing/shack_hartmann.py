"""A geometric Shack-Hartmann sensor: subapertures, slopes, DM influence functions, reconstructor and noise.

The core of ``sensor.kind: shack_hartmann`` (the loop runs it through :mod:`eofnn.sim.sensing.pupil` and
:mod:`eofnn.sim.loop.sensing`). Everything here is linear algebra on a *fine grid* of phase samples:

- **Geometry** (:class:`SubapertureGeometry`). ``fried`` (the default): ``n_across - 1`` subapertures of pitch
  ``d`` (the actuator pitch) between four actuators, their corners on actuator centres; ``cell``: one ``d x d``
  subaperture centred on each actuator cell of the :class:`~eofnn.sim.grid.ActuatorGrid` (``subapertures_across``
  may be fewer, of pitch ``D / subapertures_across``). A subaperture is valid when its centre lies in the
  (obstructed) pupil and the DM spans it (every actuator less than a pitch from its square is active: Fried, its
  four corners; cell, the 3 x 3 around it); it is taken as fully lit. The fine grid has pitch ``h = d_s / m``
  (``m = samples_per_subaperture``) and puts points on every subaperture's edges; it is itself an
  :class:`ActuatorGrid` (:attr:`SubapertureGeometry.fine_grid`), so that
  ``Turbulence(..., Atmosphere(kernel="point"), fine_grid, ...)`` synthesises the exact frozen-flow phase on it.

  Why Fried by default: with symmetric influence functions the ``cell`` geometry cannot see a command alternating
  along x and smooth along y (its surface vanishes half-way between actuators, on every subaperture edge), nor the
  same along y: about ``2 n`` near-invisible modes, beside waffle, that edge effects excite; through ``fried`` tilt,
  defocus and a cubic come back within 12% (``tests/test_shack_hartmann.py``; the tilt errors measured in each
  geometry: ``docs/findings.md``). Subapertures the DM does not span (past its last actuator) see its roll-off:
  there a tilt command's slopes change sign, and the least-squares fit of every mode bends to follow them.
- **Slopes** (:attr:`SubapertureGeometry.slope_operator`, ``S``, sparse ``(2 n_sub, n_fine)``): the x slope of a
  subaperture is the mean phase on its right edge minus the mean on its left edge,
  ``s_x = <phi>_right - <phi>_left = d_s <dphi/dx>_subaperture`` (Gauss: the mean gradient over the square times its
  side, exact up to the edge quadrature: Simpson's rule for even ``m``, exact for cubics along the edge; the
  trapezoid rule for odd ``m``). **Slope unit: nm of OPD difference across the subaperture** (gradient x ``d_s``),
  so that noise and aliasing are in nm like everything else. Rows: every x slope, then every y slope, subapertures
  in row-major order (y then x).
- **Influence functions** (:mod:`eofnn.sim.sensing.least_squares`, as the reconstructor): Gaussian, OOPAO's shape and
  default coupling (``OOPAO/DeformableMirror.py``: ``exp(-r² / (2 c²))``, ``c = d / sqrt(2 ln(1 / coupling))``, so the
  value at a neighbour one pitch away is ``coupling``; default ``mechCoupling = 0.35``), 1 nm at the actuator per nm
  of command, sparse ``(n_fine, K)``, cut where below :data:`~eofnn.sim.sensing.least_squares.INFLUENCE_FLOOR`.
- **Interaction matrix and reconstructor**: ``D = S IF`` ``(2 n_sub, K)`` (nm of slope per nm of command) and the
  least-squares ``R = V_k Σ_k^-1 U_k^T`` ``(K, 2 n_sub)`` by truncated SVD: singular values at or below
  ``relative_cut`` x the largest are dropped. Default cut ``min(0.1, 3 / n_sub_across)``
  (:func:`default_relative_cut`): in this zonal basis a cut above 0.1 starts removing the lowest orders (a tilt's
  reconstruction error against the cut: ``docs/findings.md``): the lowest spatial frequencies have singular values
  ``~ 2 pi / n`` of the largest's order, the modes the subaperture grid barely sees (piston, waffle, edge modes)
  fall below. The noise propagation grows as the cut falls (the kept modes nearest it dominate it).
- **Noise** (:class:`~eofnn.sim.sensing.detector.Detector`): photons per subaperture and frame from the guide star's
  magnitude (OOPAO's photometry table), centroid noise by Rousset's formulas (phase difference across the subaperture,
  rad², at the sensing wavelength; the photon term with the coefficient exact for a Gaussian spot by default), in the
  slope unit above.

What ``tests/test_shack_hartmann.py`` checks against theory (Fried, ``m = 4``, coupling 0.35, default cut; the
measured values themselves: ``docs/findings.md``):

- noise propagation ``p = trace(R R^T) / K`` (command variance per unit slope-noise variance) within 20% of the
  periodic Fourier-domain least-squares filter's (the pupil's rim adds ``~4 / n``); the kept modes nearest the cut
  dominate it, not the ``0.2 ln n`` of the lowest orders;
- aliasing of exact frozen flow, ``IF R S (phi - IF y_fit)``, away from the rim, within 20% of the Fourier-domain
  aliasing spectrum's share of the fitting variance (the rim amplifies it);
- Rousset's centroid noise within 25% of a Monte Carlo of centre-of-gravity centroids on a pixelated detector.

In the loop: the sensor's view is ``R (S phi + n)`` (:meth:`ShackHartmannSensor.measure`), white slope noise reaching
the commands with covariance ``sigma² R R^T``; ``R S`` stays two factors (one dense ``K x n_fine`` matrix: 216 MB at
40 across). ``pupil_diameter_m`` and ``lit_fraction`` give a pupil inside the actuator grid and partly lit rim
subapertures (:mod:`eofnn.sim.sensing.subapertures`), as OOPAO builds them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar

import numpy as np
import scipy.sparse as sp
import torch

from eofnn.errors import ConfigError, require
from eofnn.sim.grid import MAX_N_ACROSS, ActuatorGrid
from eofnn.sim.sensing.constants import GEOMETRIES, MECHANICAL_COUPLING, SHACK_HARTMANN_CONSTRAINTS  # noqa: F401 (GEOMETRIES: re-exported)
from eofnn.sim.sensing.least_squares import default_relative_cut, influence_functions, least_squares_reconstructor
from eofnn.sim.sensing.subapertures import edge_weights, lattice, lit_fractions, partly_lit_rows
from eofnn.validation import Constraint, Interval, check_value, validated


class SubapertureGeometry:
    """Where the subapertures lie, the fine grid of phase samples that covers their edges, and the slope operator.

    Parameters
    ----------
    grid : ActuatorGrid
        The DM's actuators (pitch ``d = grid.pitch_m``, metres).
    geometry : {"fried", "cell"}
        ``fried``: ``n_across - 1`` subapertures of pitch ``d`` whose corners are actuators; ``cell``: subapertures
        of pitch ``D / subapertures_across`` centred on the pupil (one per actuator cell by default).
    samples_per_subaperture : int
        ``m``: fine-grid intervals per subaperture side (fine pitch ``h = d_s / m``), 1 to 16.
    subapertures_across : int or None
        ``cell`` only: subapertures across the pupil diameter, 2 to ``n_across`` (default ``n_across``).

    Attributes
    ----------
    pitch_m : float
        Subaperture side ``d_s`` (m).
    centres_m : ndarray
        ``(n_sub, 2)`` (x, y) centres of the valid subapertures (m), row-major (y then x).
    fine_grid : ActuatorGrid
        The fine grid (pitch ``h``; its active points are the fine points, in its own order).
    slope_operator : scipy.sparse.csr_matrix
        ``S`` ``(2 n_sub, n_fine)``: fine-point OPD (nm) to slopes (nm of OPD difference across a subaperture).
    """

    def __init__(self, grid: ActuatorGrid, geometry: str = "fried", samples_per_subaperture: int = 4,
                 subapertures_across: int | None = None, pupil_diameter_m: float | None = None,
                 lit_fraction: float | None = None) -> None:
        # The arguments are a ShackHartmann config's, checked there once (its fields, and ShackHartmann.check_fits
        # against the grid); what is refused here needs the geometry itself.
        self.pupil_diameter_m = grid.diameter_m if pupil_diameter_m is None else float(pupil_diameter_m)
        self.lit_fraction = lit_fraction
        n = grid.n_across
        if geometry == "fried":
            n_sub, sensor_m = n - 1, grid.diameter_m - grid.pitch_m
        else:
            n_sub = n if subapertures_across is None else subapertures_across
            sensor_m = grid.diameter_m
        m = samples_per_subaperture
        self.grid, self.geometry, self.samples_per_subaperture = grid, geometry, m
        self.subapertures_across = n_sub
        self.pitch_m = sensor_m / n_sub
        h = self.pitch_m / m
        self.fine_pitch_m = h

        # Valid subapertures: centre inside the pupil annulus (the actuator grid's own rule and tolerance) ...
        centres_1d = (np.arange(n_sub) + 0.5) * self.pitch_m - sensor_m / 2
        yy, xx = np.meshgrid(centres_1d, centres_1d, indexing="ij")
        r = np.hypot(xx, yy)
        tol = 1e-9 * grid.diameter_m
        pupil = self.pupil_diameter_m
        if lit_fraction is None:
            valid = (r <= pupil / 2 + tol) & (r >= grid.obstruction * pupil / 2 - tol)
        else:  # at least lit_fraction of its area lit (OOPAO's lightRatio), on 64 x 64 samples
            lit = lit_fractions(np.stack([xx.ravel(), yy.ravel()], 1), self.pitch_m, pupil, grid.obstruction * pupil,
                                 64).reshape(xx.shape)
            valid = lit >= lit_fraction - 1e-9
        # ... and the DM spans it: every lattice actuator less than a pitch from its square is active (Fried: its four
        # corners; cell: the 3 x 3 around it). Otherwise the DM's roll-off beyond its last actuator reverses the
        # slopes of a tilt there and the least-squares fit of every mode bends to follow them.
        from scipy.spatial import cKDTree

        near = cKDTree(lattice(grid)).query_ball_point(np.stack([xx.ravel(), yy.ravel()], 1),
                                                         self.pitch_m / 2 + grid.pitch_m * (1 - 1e-6), p=np.inf)
        active = grid.mask.ravel()
        valid &= np.array([active[i].all() for i in near]).reshape(valid.shape)
        require(valid.sum() >= 1, f"geometry {geometry!r} on {n} actuators across leaves no subaperture in the pupil")
        self.valid = valid
        rows, cols = np.nonzero(valid)
        self.centres_m = np.stack([xx[valid], yy[valid]], axis=1)
        # Fraction of each valid subaperture's area inside the pupil: 1 where the rule takes it as fully lit.
        self.illumination = lit[valid] if lit_fraction is not None else np.ones(len(rows))

        # The fine grid: points at -sensor/2 + i h (i = -p .. n_sub m + p), an ActuatorGrid of n_sub m + 1 + 2p
        # points across whose circular mask holds every valid subaperture's corners.
        corner = float(np.hypot(np.abs(self.centres_m[:, 0]) + self.pitch_m / 2,
                                np.abs(self.centres_m[:, 1]) + self.pitch_m / 2).max())
        pad = max(0, math.ceil((corner - sensor_m / 2) / h - 0.5 - 1e-9))
        n_fine = n_sub * m + 1 + 2 * pad
        require(n_fine <= MAX_N_ACROSS,
                f"samples_per_subaperture={m} with {n_sub} subapertures across needs a fine grid of {n_fine} points "
                f"across: allowed at most {MAX_N_ACROSS}; use fewer samples per subaperture")
        self.fine_grid = ActuatorGrid(n_fine * h, n_fine, 0.0)
        lookup = np.full((n_fine, n_fine), -1, dtype=np.int64)
        lookup[self.fine_grid.mask] = np.arange(self.fine_grid.n_actuators)

        # S: x slope = sum_k w_k (phi[row0 + k, col0 + m] - phi[row0 + k, col0]), y likewise with rows and columns
        # exchanged; (row0, col0) the subaperture's lower-left fine point.
        w = edge_weights(m)
        k = np.arange(m + 1)
        row0, col0 = pad + rows * m, pad + cols * m
        n_valid = len(rows)
        sub = np.arange(n_valid)[:, None]
        ones = np.ones((n_valid, m + 1))
        entries = []
        for axis in (0, 1):  # 0: x slopes, 1: y slopes
            along_r = row0[:, None] + (k if axis == 0 else 0 * k)
            along_c = col0[:, None] + (0 * k if axis == 0 else k)
            step_r, step_c = (0, m) if axis == 0 else (m, 0)
            for sign, dr, dc in ((1.0, step_r, step_c), (-1.0, 0, 0)):
                idx = lookup[along_r + dr, along_c + dc]
                if (idx < 0).any():  # the padding is computed to prevent it
                    raise AssertionError("a subaperture edge point lies outside the fine grid")
                entries.append((axis * n_valid + sub * ones, idx, sign * w * ones))
        r_idx, c_idx, vals = (np.concatenate([e[j].ravel() for e in entries]) for j in range(3))
        partial = np.flatnonzero(self.illumination < 1 - 1e-9)
        if len(partial):  # partly lit: the lit area's mean gradient (the centroid of its spot), not the edges'
            keep = ~np.isin(r_idx % n_valid, partial)
            extra = partly_lit_rows(partial, row0, col0, m, h, n_valid, lookup, pupil, grid.obstruction * pupil)
            r_idx, c_idx, vals = (np.concatenate([a[keep], b]) for a, b in zip((r_idx, c_idx, vals), extra, strict=True))
        self.slope_operator = sp.csr_matrix((vals, (r_idx.astype(np.int64), c_idx)),
                                            shape=(2 * n_valid, self.fine_grid.n_actuators))
        self.slope_operator.sum_duplicates()

    @property
    def n_subapertures(self) -> int:
        """Number of valid subapertures."""
        return len(self.centres_m)

    @property
    def n_fine(self) -> int:
        """Number of fine points (the fine grid's active points)."""
        return self.fine_grid.n_actuators

    @cached_property
    def fine_positions_m(self) -> np.ndarray:
        """``(n_fine, 2)`` (x, y) of the fine points (m), centred on the pupil."""
        return self.fine_grid.positions_m

    @cached_property
    def fine_in_pupil(self) -> np.ndarray:
        """Boolean ``(n_fine,)``: fine points inside the (obstructed) pupil, where the residual is scored."""
        r = np.hypot(*self.fine_positions_m.T)
        g, tol, pupil = self.grid, 1e-9 * self.grid.diameter_m, self.pupil_diameter_m
        return (r <= pupil / 2 + tol) & (r >= g.obstruction * pupil / 2 - tol)


    @cached_property
    def fine_in_subapertures(self) -> np.ndarray:
        """Boolean ``(n_fine,)``: fine points in (or on the edge of) a valid subaperture, the area the sensor sees."""
        from scipy.spatial import cKDTree

        counts = cKDTree(self.centres_m).query_ball_point(self.fine_positions_m, self.pitch_m / 2 * (1 + 1e-9),
                                                           p=np.inf, return_length=True)
        return np.asarray(counts) > 0


@dataclass(frozen=True)
@validated
class ShackHartmann:
    """A geometric Shack-Hartmann sensor and its least-squares reconstructor (the config; :meth:`build` makes one).

    Parameters
    ----------
    geometry : {"fried", "cell"}
        Subapertures between four actuators (default), or centred on the actuator cells (:class:`SubapertureGeometry`;
        ``cell`` leaves about ``2 n`` stripe modes unseen).
    samples_per_subaperture : int
        Fine-grid intervals per subaperture side ``m`` (fine pitch ``d_s / m``); Simpson's rule on the edges for even
        ``m``. 4 by default (``tests/test_shack_hartmann.py`` measures what 2 loses).
    subapertures_across : int or None
        ``cell`` only: subapertures across the pupil (default: one per actuator).
    mechanical_coupling : float
        Influence of an actuator at its neighbour, in (0, 1) (OOPAO's default 0.35).
    relative_cut : float or None
        Singular values of ``D`` at or below this fraction of the largest are dropped from ``R``, in [0.001, 1]
        (1 drops every mode and is refused when ``R`` is built); ``None``: ``3 / subapertures_across``
        (:func:`default_relative_cut`).
    pupil_diameter_m : float or None
        The lit pupil (m), at most the grid's diameter; ``None``: the grid's. Where the residual is scored and the
        DM's fit of the phase is made. OOPAO's pupil ends with its subapertures, half a pitch inside its Fried DM's
        last actuators: an actuator grid of ``N + 1`` across at pitch ``d`` with ``pupil_diameter_m = N d``.
    lit_fraction : float or None
        ``None``: a subaperture is valid when its centre lies in the pupil, and taken as fully lit. A number in
        (0, 1]: valid when at least that fraction of its area is lit (OOPAO's ``lightRatio``, 0.5 there); a partly lit
        one measures its lit area's mean gradient (its spot's centroid) and has photon noise ``1 / lit`` times the
        variance of a fully lit one's.
    """

    geometry: str = "fried"
    samples_per_subaperture: int = 4
    subapertures_across: int | None = None
    mechanical_coupling: float = MECHANICAL_COUPLING
    relative_cut: float | None = None
    pupil_diameter_m: float | None = None
    lit_fraction: float | None = None

    _constraints: ClassVar[dict[str, Constraint]] = SHACK_HARTMANN_CONSTRAINTS

    def build(self, grid: ActuatorGrid) -> ShackHartmannSensor:
        """The sensor on ``grid``: geometry, slope operator, influence functions, ``D`` and ``R``."""
        return ShackHartmannSensor(grid, self)

    def check_fits(self, grid: ActuatorGrid) -> None:
        """Refuse, in one line, what these (already checked) fields cannot build on ``grid``: a lit pupil wider than
        the grid, or subapertures across that the geometry cannot have there. The sensor is built past this check
        without checking its arguments again."""
        if self.pupil_diameter_m is not None:
            check_value("sensor.pupil_diameter_m", self.pupil_diameter_m,
                        Interval(0, grid.diameter_m, closed="right",
                                 unit=f"m (the actuator grid is {grid.diameter_m:g} m across)"))
        n = grid.n_across
        if self.geometry == "cell":
            check_value("subapertures_across", n if self.subapertures_across is None else self.subapertures_across,
                        Interval(2, n, integer=True, unit=f"subapertures across; the grid has {n} actuators across"))
        elif self.subapertures_across not in (None, n - 1):
            raise ConfigError(f"subapertures_across={self.subapertures_across!r} is invalid for geometry 'fried' on "
                              f"{n} actuators across: it has {n - 1} (one between each pair of actuators); leave it "
                              "unset")


class ShackHartmannSensor:
    """A built :class:`ShackHartmann` on an actuator grid (numpy and scipy inside, torch tensors at the boundary).

    Attributes
    ----------
    geometry : SubapertureGeometry
        Subapertures, fine grid, slope operator ``S``.
    influence : scipy.sparse.csr_matrix
        ``IF`` ``(n_fine, K)``: fine-point surface (nm) per nm of command.
    interaction_matrix : ndarray
        ``D = S IF`` ``(2 n_sub, K)``: slopes (nm) per nm of command.
    reconstructor : ndarray
        ``R`` ``(K, 2 n_sub)``: commands (nm) per nm of slope.
    kept_modes : int
        Singular modes of ``D`` kept in ``R``.
    relative_cut : float
        The cut used.
    """

    def __init__(self, grid: ActuatorGrid, config: ShackHartmann = ShackHartmann()) -> None:
        config.check_fits(grid)
        self.grid, self.config = grid, config
        self.geometry = SubapertureGeometry(grid, config.geometry, config.samples_per_subaperture,
                                            config.subapertures_across, config.pupil_diameter_m, config.lit_fraction)
        self.influence = influence_functions(grid, self.geometry.fine_positions_m, config.mechanical_coupling)
        self.interaction_matrix = np.asarray((self.geometry.slope_operator @ self.influence).todense())
        self.relative_cut = (config.relative_cut if config.relative_cut is not None
                             else default_relative_cut(self.geometry.subapertures_across))
        self.reconstructor, self.kept_modes, self.singular_values = least_squares_reconstructor(
            self.interaction_matrix, self.relative_cut)

    @property
    def n_slopes(self) -> int:
        """``2 n_sub``: x slopes then y slopes."""
        return 2 * self.geometry.n_subapertures

    @cached_property
    def slope_noise_scale(self) -> np.ndarray:
        """``(2 n_sub,)``: each slope's noise RMS relative to a fully lit subaperture's, ``1 / sqrt(lit fraction)``
        (photon noise; all ones unless ``lit_fraction`` is set)."""
        return np.tile(1.0 / np.sqrt(self.geometry.illumination), 2)

    def slopes(self, phase_fine: torch.Tensor) -> torch.Tensor:
        """``S phi``: ``(..., n_fine)`` fine-point OPD (nm) to ``(..., 2 n_sub)`` slopes (nm of OPD difference across
        each subaperture)."""
        phase = _last_dim(phase_fine, self.geometry.n_fine, "phase_fine", "fine points of the sensor's grid")
        flat = phase.reshape(-1, phase.shape[-1]).numpy()
        return torch.as_tensor(np.asarray((self.geometry.slope_operator @ flat.T).T)).reshape(
            *phase.shape[:-1], self.n_slopes)

    def reconstruct(self, slopes: torch.Tensor, reconstructor=None) -> torch.Tensor:
        """``R s``: ``(..., 2 n_sub)`` slopes (nm) to ``(..., K)`` commands (nm); ``reconstructor`` ``(K, 2 n_sub)``
        replaces :attr:`reconstructor` when given (one :class:`ConfigError` line if its shape does not fit)."""
        r = self.reconstructor if reconstructor is None else np.asarray(
            reconstructor.detach().cpu().numpy() if isinstance(reconstructor, torch.Tensor) else reconstructor,
            dtype=np.float64)
        require(r.shape == (self.grid.n_actuators, self.n_slopes),
                f"reconstructor of shape {r.shape} does not fit: expected ({self.grid.n_actuators}, {self.n_slopes}) "
                f"({self.grid.n_actuators} actuators x {self.n_slopes} slopes)")
        s = _last_dim(slopes, self.n_slopes, "slopes", f"x then y slopes of {self.geometry.n_subapertures} "
                      "subapertures")
        return s @ torch.as_tensor(r).T

    def sense(self, phase_fine: torch.Tensor) -> torch.Tensor:
        """The sensor's view in command space, ``R S phi`` (nm): what the loop's ``wfs`` will be, noise aside."""
        return self.reconstruct(self.slopes(phase_fine))

    def measure(self, phase_fine: torch.Tensor, slope_noise_nm: float = 0.0,
                generator: torch.Generator | None = None) -> torch.Tensor:
        """``R (S phi + n)``: the sensor's reading in command space (nm), ``n`` white slope noise of RMS
        ``slope_noise_nm`` (nm; e.g. ``sqrt(Detector.slope_noise_variance_nm2(...))``) drawn from ``generator``."""
        check_value("slope_noise_nm", slope_noise_nm, Interval(0, None, unit="nm RMS per slope"))
        slopes = self.slopes(phase_fine)
        if slope_noise_nm > 0:
            slopes = slopes + slope_noise_nm * torch.as_tensor(self.slope_noise_scale) * torch.randn(
                slopes.shape, generator=generator, dtype=slopes.dtype)
        return self.reconstruct(slopes)

    def dm_surface(self, commands: torch.Tensor) -> torch.Tensor:
        """``IF y``: ``(..., K)`` commands (nm) to ``(..., n_fine)`` DM surface (nm) on the fine points."""
        y = _last_dim(commands, self.grid.n_actuators, "commands", "actuators")
        flat = y.reshape(-1, y.shape[-1]).numpy()
        return torch.as_tensor(np.asarray((self.influence @ flat.T).T)).reshape(*y.shape[:-1], self.geometry.n_fine)

    def noise_propagation(self) -> float:
        """``p = trace(R W R^T) / K``: the mean per-actuator command variance per unit variance of a fully lit
        subaperture's white slope noise (``W``: :attr:`slope_noise_scale` squared, the identity unless partly lit
        subapertures are modelled)."""
        return float((self.reconstructor ** 2 * self.slope_noise_scale ** 2).sum() / self.grid.n_actuators)


def _last_dim(values: torch.Tensor, size: int, name: str, what: str) -> torch.Tensor:
    values = torch.as_tensor(values).to(torch.float64)
    require(values.ndim >= 1 and values.shape[-1] == size,
            f"{name} of shape {tuple(values.shape)} does not fit: its last dimension must be {size} ({what})")
    return values.cpu()
