"""Raw contrast behind a perfect coronagraph, from the residual phase on the actuator grid (what on-sky papers plot).

Per sampled frame the residual ``eps`` (nm) becomes a pupil field ``A exp(i 2 pi eps / lambda)`` on the actuator
grid (one sample per actuator, the pupil mask as amplitude). A perfect coronagraph removes the pupil-averaged
field, ``E_c = A (exp(i phi) - <exp(i phi)>_pupil)`` (Cavarlaz / Guyon's ideal coronagraph); its focal-plane
intensity, zero-padded ``padding`` times (so ``padding`` pixels per lambda/D), is normalised by the peak of the
unobstructed PSF. The mean over frames is averaged azimuthally: raw contrast against separation in lambda/D, up to
the grid's control radius ``n_across / 2``.
"""

from __future__ import annotations

import math

import torch

from eofnn.sim.grid import ActuatorGrid
from eofnn.validation import Interval, check_value

#: Separations (lambda/D) reported in metrics.json.
REPORTED_SEPARATIONS = (2.0, 3.0, 5.0, 10.0)
#: Where :func:`halo` starts (lambda/D): the PSF's core is left out.
HALO_FROM_LOD = 0.5
#: Frames whose focal planes are computed together (:meth:`RawContrast._focal_planes`).
_BLOCK_FRAMES = 8


class RawContrast:
    """Accumulates the coronagraphic intensity of every ``every``-th settled frame; feed it through ``on_chunk``.

    Parameters
    ----------
    grid : ActuatorGrid
        Where the residual is sampled.
    wavelength_m : float
        Science wavelength in metres.
    settle_frames : int
        Frames skipped at the start.
    every : int
        One frame in ``every`` is propagated (frames a few ms apart are nearly the same speckles).
    padding : int
        Zero padding of the pupil: focal-plane pixels per lambda/D.
    pupil : ndarray of bool, optional
        A Shack-Hartmann scenario: ``grid`` is the sensor's fine grid, ``pupil`` its points inside the telescope's
        pupil (of diameter ``pupil_diameter_m``), and the residual comes from ``arrays["pupil_residual"](frame)``
        (:func:`~eofnn.sim.loop.runner.run_loop`): fitting error and aliasing are in the speckles. Separations are
        still in lambda/D of the pupil, up to the actuators' control radius.
    pupil_diameter_m : float, optional
        The telescope's diameter, with ``pupil``.
    control_radius_lod : float, optional
        With ``pupil``: the profile's outer edge (lambda/D), the actuators' ``n_across / 2``.
    """

    def __init__(self, grid: ActuatorGrid, wavelength_m: float, settle_frames: int = 0, every: int = 10,
                 padding: int = 4, pupil=None, pupil_diameter_m: float | None = None,
                 control_radius_lod: float | None = None) -> None:
        check_value("every", every, Interval(1, 10_000, integer=True))
        check_value("padding", padding, Interval(2, 16, integer=True))
        self.grid, self.wavelength_m, self.settle, self.every, self.padding = grid, wavelength_m, settle_frames, every, padding
        n = grid.n_across
        self._size = padding * n
        indices = grid.indices if pupil is None else grid.indices[pupil]
        self._pupil = pupil is not None
        # Focal-plane pixels per lambda/D of the pupil: `padding` on the actuator grid (its side is the diameter).
        self._pixels_per_lod = padding if pupil is None else padding * n * grid.pitch_m / pupil_diameter_m
        self._limit_lod = n / 2 if pupil is None else control_radius_lod
        self._index = torch.as_tensor(indices[:, 0] * self._size + indices[:, 1])
        amplitude = torch.zeros(self._size * self._size, dtype=torch.complex128)
        amplitude[self._index] = 1.0
        self._peak = float(torch.fft.fft2(amplitude.view(self._size, self._size)).abs().max() ** 2)
        self._sum: torch.Tensor | None = None
        self._phase_power: torch.Tensor | None = None  # sum over frames of |FFT(pupil x piston-free residual)|^2, nm^2
        self._count = 0
        #: Per turbulence realisation (the first axis of ``eps``): the sum of its frames' intensities, and their count.
        self._realisation_sums: torch.Tensor | None = None
        self._realisation_count = 0
        self._planes: torch.Tensor | None = None  # the focal planes' buffer, reused call after call

    def __call__(self, first_frame: int, arrays: dict[str, torch.Tensor]) -> None:
        eps = arrays["eps"]
        frames = [i for i in range(eps.shape[1]) if (first_frame + i) >= self.settle and (first_frame + i) % self.every == 0]
        if not frames:
            return
        if self._pupil:
            residual = torch.stack([arrays["pupil_residual"](first_frame + i) for i in frames], 1)
            self.add(residual.reshape(-1, residual.shape[-1]), realisations=residual.shape[0])
        else:
            self.add(eps[:, frames].reshape(-1, eps.shape[-1]), realisations=eps.shape[0])

    def add(self, residual_nm: torch.Tensor, realisations: int = 1) -> None:
        """Accumulate ``(frames, points)`` residuals (nm) on the grid's points (with ``pupil``: those in the pupil),
        whatever frame they are (the caller picks them: :meth:`__call__` takes every ``every``-th settled one).

        ``realisations`` > 1: the frames are that many turbulence realisations' in turn (realisation-major, the same
        number each); each realisation's intensity is also kept on its own (:meth:`realisations_at`), the pooled sum
        being added exactly as with one."""
        flat = torch.as_tensor(residual_nm, dtype=torch.float64)
        field = torch.exp(1j * (flat * (2 * math.pi * 1e-9 / self.wavelength_m)))
        field = field - field.mean(-1, keepdim=True)  # the perfect coronagraph: no coherent part is left
        frames = self._focal_planes(field)
        intensity = frames.sum(0)
        self._sum = intensity if self._sum is None else self._sum + intensity
        per = frames.view(realisations, -1, self._size, self._size).sum(1)
        if self._realisation_sums is not None and self._realisation_sums.shape[0] != realisations:
            self._realisation_sums = None  # frames of another number of realisations: no per-realisation split
            self._realisation_count = -1
        elif self._realisation_count >= 0:
            self._realisation_sums = per if self._realisation_sums is None else self._realisation_sums + per
            self._realisation_count += field.shape[0] // realisations
        power = self._focal_planes(flat - flat.mean(-1, keepdim=True)).sum(0)
        self._phase_power = power if self._phase_power is None else self._phase_power + power
        self._count += field.shape[0]

    def _focal_planes(self, values: torch.Tensor) -> torch.Tensor:
        """``|FFT2(pupil x values)|²`` of each ``(frames, points)`` row, zero padded: ``(frames, size, size)``.

        A few frames are transformed at a time (every transform is computed on its own, so the numbers are those of
        one transform of all of them), into one buffer of focal planes kept for the next call: fresh arrays of every
        frame's padded pupil and spectrum (hundreds of MB on a Shack-Hartmann's fine grid) cost more in page faults
        than the transforms themselves."""
        rows, size = values.shape[0], self._size
        if self._planes is None or self._planes.shape[0] < rows:
            self._planes = torch.empty(rows, size, size, dtype=torch.float64)
        out = self._planes[:rows]
        pupil = torch.zeros(min(rows, _BLOCK_FRAMES), size * size, dtype=values.dtype)  # zero outside the points
        spectrum = torch.empty(pupil.shape[0], size, size, dtype=torch.complex128)
        for first in range(0, rows, _BLOCK_FRAMES):
            block = values[first: first + _BLOCK_FRAMES]
            n = block.shape[0]
            pupil[:n, self._index] = block
            torch.fft.fft2(pupil[:n].view(n, size, size), out=spectrum[:n])
            torch.abs(spectrum[:n], out=out[first: first + n]).pow_(2)
        return out

    def profile(self) -> tuple[list[float], list[float]]:
        """Separations (lambda/D, one per focal-plane pixel) and the azimuthally averaged raw contrast."""
        if self._sum is None:
            return [], []
        return self._profile(self._sum, self._count)

    def _profile(self, total: torch.Tensor, count: int) -> tuple[list[float], list[float]]:
        """The azimuthal average of ``total`` (a sum of ``count`` frames' intensities)."""
        image = torch.fft.fftshift(total / (count * self._peak))
        c = self._size // 2
        yy, xx = torch.meshgrid(torch.arange(self._size) - c, torch.arange(self._size) - c, indexing="ij")
        radius = torch.hypot(yy.double(), xx.double())
        if self._pupil:  # bins of 1 / padding lambda/D of the pupil
            radius = radius * (self.padding / self._pixels_per_lod)
            limit = int(self._limit_lod * self.padding)
        else:
            limit = self.grid.n_across * self.padding // 2  # the control radius n/2 lambda/D
        radius = torch.round(radius).long()
        sums = torch.zeros(limit + 1, dtype=torch.float64).scatter_add_(0, radius.clamp(max=limit).flatten(),
                                                                       image.flatten())
        counts = torch.zeros(limit + 1, dtype=torch.float64).scatter_add_(0, radius.clamp(max=limit).flatten(),
                                                                         torch.ones(image.numel(), dtype=torch.float64))
        separations = (torch.arange(limit) / self.padding).tolist()
        return separations, (sums[:limit] / counts[:limit]).tolist()

    def spatial_split(self) -> dict[str, float] | None:
        """Where in spatial frequency the residual lies: its piston-removed variance over the pupil, split exactly
        (Parseval on the pupil-masked residual, zero padded) between the circle inside the control radius
        (``inside_control_circle``, what a round dark hole sees), the corners of the DM's square control region
        outside that circle (``control_square_corners``, out to ``sqrt(2)`` times the radius: waffle-like patterns)
        and beyond the square (``beyond_control``: the fitting error and the DM surface's own high frequencies; only
        a Shack-Hartmann's fine grid reaches there). Each as an RMS in nm, their squares summing to the mean variance
        of the propagated frames; ``None`` with no frames."""
        if self._phase_power is None:
            return None
        power = torch.fft.fftshift(self._phase_power) / (self._count * len(self._index) * self._size ** 2)
        c = self._size // 2
        yy, xx = torch.meshgrid(torch.arange(self._size) - c, torch.arange(self._size) - c, indexing="ij")
        y, x = yy.double().abs() / self._pixels_per_lod, xx.double().abs() / self._pixels_per_lod
        circle = torch.hypot(y, x) < self._limit_lod
        square = torch.maximum(y, x) <= self._limit_lod + 1e-9  # the Nyquist row of a zonal grid is its edge
        parts = {"inside_control_circle": circle, "control_square_corners": square & ~circle,
                 "beyond_control": ~square}
        return {k: math.sqrt(float(power[mask].sum())) for k, mask in parts.items()}

    def at(self, separations: tuple[float, ...] = REPORTED_SEPARATIONS) -> dict[str, float | None]:
        """Raw contrast at the given separations (lambda/D); ``None`` beyond the control radius or with no frames."""
        return self._at(self.profile(), separations)

    def realisations_at(self, separations: tuple[float, ...] = REPORTED_SEPARATIONS) -> list[dict[str, float | None]]:
        """:meth:`at` of each turbulence realisation on its own (the spread a verdict gives); empty with no frames, or
        when chunks of different numbers of realisations were added."""
        if self._realisation_sums is None or self._realisation_count <= 0:
            return []
        return [self._at(self._profile(total, self._realisation_count), separations)
                for total in self._realisation_sums]

    def _at(self, profile: tuple[list[float], list[float]], separations: tuple[float, ...]) -> dict[str, float | None]:
        seps, values = profile
        out = {}
        for s in separations:
            index = round(s * self.padding)
            out[f"{s:g}"] = values[index] if values and index < len(values) else None
        return out


def halo(separation_lod, raw_contrast, start_lod: float = HALO_FROM_LOD) -> tuple[float, float] | None:
    """The raw contrast integrated over the focal plane from ``start_lod`` to the end of a radial profile.

    Each separation is weighted by its ring's area (``2 pi r dr``, up to the constant ``2 pi dr`` of a profile
    sampled every ``dr``). To first order in the residual phase the coronagraphic image is the residual's spatial
    power spectrum, so the halo is the residual variance at the spatial frequencies of those separations, and the
    ratio of two controllers' halos (profiles sampled alike) is their ratio of residual variance there.

    Parameters
    ----------
    separation_lod : sequence of float
        Separations (lambda/D), as :meth:`RawContrast.profile` gives them.
    raw_contrast : sequence of float or None
        The azimuthally averaged raw contrast at each (``None``: not measured, left out).
    start_lod : float
        The smallest separation counted (lambda/D).

    Returns
    -------
    tuple of float, or None
        ``(sum of r * contrast(r), reach)``: the halo (lambda/D, contrast times separation summed) and the largest
        separation counted (lambda/D: the control radius's inscribed circle for a profile of :class:`RawContrast`);
        ``None`` when no separation is counted.
    """
    pairs = [(r, v) for r, v in zip(separation_lod, raw_contrast, strict=True) if r >= start_lod and v is not None]
    return (sum(r * v for r, v in pairs), max(r for r, _ in pairs)) if pairs else None


def scenario_contrast(scenario, wavelength_m: float, settle_frames: int) -> RawContrast:
    """The raw contrast of a run in ``scenario``: from the actuators' residual (zonal sensor), or from the residual
    over the pupil on a Shack-Hartmann's fine grid, every :data:`~eofnn.sim.loop.sensing.PHASE_EVERY`-th frame."""
    if not scenario.sensor.is_shack_hartmann:
        return RawContrast(scenario.grid, wavelength_m, settle_frames)
    from eofnn.sim.loop.sensing import PHASE_EVERY, loop_operators

    geometry = loop_operators(scenario.grid, scenario.sensor.shack_hartmann()).sensor.geometry
    return RawContrast(geometry.fine_grid, wavelength_m, settle_frames, every=PHASE_EVERY, pupil=geometry.fine_in_pupil,
                       pupil_diameter_m=scenario.grid.diameter_m, control_radius_lod=scenario.grid.n_across / 2)
