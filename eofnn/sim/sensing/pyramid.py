"""A diffractive modulated pyramid wavefront sensor: its config, calibration, reconstructor and noise.

The pyramid is a four-faced glass prism at the focal plane: each face tilts the light that falls on it, so a relay
lens makes four images of the pupil on the detector, and the phase's gradients (or, unmodulated, the phase itself
above the PSF's core) become intensity differences between them. Everything is in torch, batched over frames,
on the device of the phase it is given (the calibration on the CPU in double precision by default).

- **Optics, modulation, flux, signals**: :mod:`eofnn.sim.sensing.pyramid_optics` (OOPAO's geometry).
- **Calibration** (:class:`PyramidSensor`): the DM's Gaussian influence functions
  (:func:`~eofnn.sim.sensing.least_squares.influence_functions`) at the pupil's points, the interaction matrix
  ``D`` by push-pull of each actuator (``(s(+a IF_k) - s(-a IF_k)) / 2a``, ``a = push_pull_nm``) and the truncated
  least-squares reconstructor (:func:`~eofnn.sim.sensing.least_squares.least_squares_reconstructor`).
- **Optical gains** (:mod:`eofnn.sim.sensing.optical_gains`): the response to a small probe about a residual
  against the one about a flat wavefront, per mode; in the loop: :mod:`eofnn.sim.loop.pyramid`.

``tests/test_pyramid.py`` checks it against theory (linearity range against modulation, sensitivity against
spatial frequency, optical gains, flux, push-pull symmetry, noise), ``tests/test_pyramid_theory.py`` the tip's
linearity range and the photon-noise propagation per Fourier mode against modulation, and ``experiments/pyramid/``
against OOPAO's.
"""


from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from eofnn.errors import require
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.sensing.constants import PYRAMID_CONSTRAINTS
from eofnn.sim.sensing.detector import PHOTOMETRY
from eofnn.sim.sensing.least_squares import (
    MECHANICAL_COUPLING,
    default_relative_cut,
    influence_functions,
    least_squares_reconstructor,
)
from eofnn.sim.sensing.optical_gains import kl_modes, modal_optical_gains, optical_gains
from eofnn.sim.sensing.pyramid_optics import (
    SIGNALS,
    PyramidOptics,
    PyramidSignals,
    as_phase,
    default_modulation_points,
)
from eofnn.validation import Constraint, Interval, check_value, validated

#: The optics, signals and optical gains, importable from here too.
__all__ = ["SIGNALS", "Pyramid", "PyramidOptics", "PyramidSensor", "PyramidSignals", "default_modulation_points",
           "kl_modes", "modal_optical_gains", "optical_gains"]


@dataclass(frozen=True)
@validated
class Pyramid:
    """A diffractive modulated pyramid sensor and its reconstructor (the config; :meth:`build` makes one).

    Parameters
    ----------
    modulation_lambda_over_d : float
        Modulation radius (``lambda / D`` at the sensing wavelength), 0 for none; at most ``n / 2 - 1`` for ``n``
        pupil points across.
    pixels_across : int or None
        Detector pixels across each pupil image; ``None``: one per actuator pitch across the pupil.
    samples_per_pixel : int
        Pupil points per detector pixel along each axis (the phase is sampled on ``pixels_across *
        samples_per_pixel`` points across the pupil; their product must be even).
    separation_pixels : int
        Detector pixels between the pupil images (even; OOPAO's ``n_pix_separation``, 2).
    modulation_points : int or None
        Points on the modulation circle; ``None``: ``4 ceil(2 pi r / 4)`` (OOPAO's).
    light_ratio : float
        A detector pixel is valid where a frame with ``calibration_modulation_lambda_over_d`` of modulation reaches
        this fraction of its maximum, in [0, 1) (OOPAO's ``lightRatio``).
    calibration_modulation_lambda_over_d : float
        The modulation of that frame (``lambda / D``), capped at ``n / 2 - 1`` (OOPAO's ``calibModulation``, 50).
    signal : {"slopes_maps", "full_frame"}
        ``slopes_maps`` (``s_x``, ``s_y`` normalised by the mean flux of the four images) or the full frame's valid
        pixels normalised by their mean.
    band : str
        Photometric band of the sensing (a key of :data:`~eofnn.sim.sensing.detector.PHOTOMETRY`): its wavelength
        turns OPD into phase, its zero point gives the photons.
    push_pull_nm : float
        Amplitude of the calibration's push-pull (nm of command; small against the wavelength).
    mechanical_coupling : float
        The DM's influence at a neighbouring actuator, in (0, 1).
    relative_cut : float or None
        The reconstructor's relative singular-value cut; ``None``: ``min(0.1, 3 / pixels_across)``.
    pupil_diameter_m : float or None
        The lit pupil (m), at most the grid's diameter; ``None``: the grid's.
    """

    modulation_lambda_over_d: float = 3.0
    pixels_across: int | None = None
    samples_per_pixel: int = 2
    separation_pixels: int = 2
    modulation_points: int | None = None
    light_ratio: float = 0.1
    calibration_modulation_lambda_over_d: float = 50.0
    signal: str = "slopes_maps"
    band: str = "I"
    push_pull_nm: float = 1.0
    mechanical_coupling: float = MECHANICAL_COUPLING
    relative_cut: float | None = None
    pupil_diameter_m: float | None = None

    _constraints: ClassVar[dict[str, Constraint]] = PYRAMID_CONSTRAINTS

    @property
    def wavelength_nm(self) -> float:
        """The band's wavelength (nm)."""
        return PHOTOMETRY[self.band][0] * 1e9

    def build(self, grid: ActuatorGrid) -> PyramidSensor:
        """The sensor on ``grid``: optics, valid pixels, influence functions, ``D`` and ``R``."""
        return PyramidSensor(grid, self)


def pupil_grid(grid: ActuatorGrid, config: Pyramid) -> ActuatorGrid:
    """The pyramid's pupil points on ``grid`` (``pixels_across * samples_per_pixel`` across the lit pupil), or one
    :class:`~eofnn.errors.ConfigError` line saying why the pyramid cannot be built there."""
    pupil_m = grid.diameter_m if config.pupil_diameter_m is None else config.pupil_diameter_m
    check_value("sensor.pupil_diameter_m", pupil_m,
                Interval(0, grid.diameter_m, closed="right", unit=f"m (the actuator grid is {grid.diameter_m:g} m "
                         "across)"))
    pixels = config.pixels_across if config.pixels_across is not None else max(2, round(pupil_m / grid.pitch_m))
    n = pixels * config.samples_per_pixel
    require(n % 2 == 0, f"pixels_across x samples_per_pixel = {pixels} x {config.samples_per_pixel} is invalid: "
                        "it must be even (the pupil is centred between four focal-plane points)")
    require(config.modulation_lambda_over_d <= n / 2 - 1,
            f"modulation_lambda_over_d={config.modulation_lambda_over_d!r} is invalid on {n} pupil points across: "
            f"allowed up to {n / 2 - 1:g} (raise pixels_across or samples_per_pixel)")
    return ActuatorGrid(pupil_m, n, grid.obstruction)


class PyramidSensor:
    """A built :class:`Pyramid` on an actuator grid (torch inside; the reconstructor by numpy's eigen-solver).

    Attributes
    ----------
    pupil_grid : ActuatorGrid
        The pupil's sample points (``n = pixels_across * samples_per_pixel`` across the lit pupil; its active points
        are the pupil's, in row-major order): phase is given there, as on a Shack-Hartmann's fine grid.
    optics : PyramidOptics
    signals : PyramidSignals
        Valid pixels, reference, processing.
    influence : scipy.sparse.csr_matrix
        ``IF`` ``(n_pupil, K)``: pupil-point surface (nm) per nm of command (peak-1 Gaussians).
    interaction_matrix : ndarray
        ``D`` ``(n_signals, K)``: signal per nm of command (push-pull of ``push_pull_nm``).
    reconstructor : ndarray
        ``R`` ``(K, n_signals)``: nm of command per unit of signal.
    kept_modes : int
    relative_cut : float
    """

    def __init__(self, grid: ActuatorGrid, config: Pyramid = Pyramid()) -> None:
        self.grid, self.config = grid, config
        self.pupil_grid = pupil_grid(grid, config)
        pixels = self.pupil_grid.n_across // config.samples_per_pixel
        self.optics = PyramidOptics(self.pupil_grid.mask, pixels, config.samples_per_pixel, config.separation_pixels,
                                    config.modulation_lambda_over_d, config.modulation_points, config.wavelength_nm)
        self.signals = PyramidSignals(self.optics, config.signal, config.light_ratio,
                                      config.calibration_modulation_lambda_over_d)
        self.influence = influence_functions(grid, self.pupil_grid.positions_m, config.mechanical_coupling)
        self.interaction_matrix = self.calibrate()
        self.relative_cut = config.relative_cut if config.relative_cut is not None else default_relative_cut(pixels)
        self.reconstructor, self.kept_modes, self.singular_values = least_squares_reconstructor(
            self.interaction_matrix, self.relative_cut)

    @property
    def n_pupil(self) -> int:
        """Pupil points the phase is given on."""
        return self.optics.n_pupil

    @property
    def n_signals(self) -> int:
        return self.signals.n_signals

    def signal(self, phase_nm: torch.Tensor) -> torch.Tensor:
        """Noise-free signals ``(..., n_signals)`` of ``(..., n_pupil)`` pupil OPD (nm)."""
        return self.signals.process(self.optics.frames(as_phase(phase_nm, self.n_pupil)))

    def response(self, probes_nm: torch.Tensor, around_nm: torch.Tensor | None = None,
                 amplitude_nm: float | None = None) -> torch.Tensor:
        """Push-pull response ``(M, n_signals)`` per nm of each of ``(M, n_pupil)`` probe shapes (nm per unit),
        about ``around_nm`` ``(n_pupil,)`` (a flat wavefront if ``None``): ``(s(r + a p) - s(r - a p)) / 2a``,
        ``a = amplitude_nm`` (the config's ``push_pull_nm`` if ``None``)."""
        a = self.config.push_pull_nm if amplitude_nm is None else amplitude_nm
        check_value("amplitude_nm", a, Interval(0, None, closed="neither", unit="nm"))
        probes = as_phase(probes_nm, self.n_pupil).reshape(-1, self.n_pupil)
        base = torch.zeros(self.n_pupil, dtype=probes.dtype, device=probes.device) if around_nm is None else \
            as_phase(around_nm, self.n_pupil).reshape(self.n_pupil).to(probes)
        pushed = self.signal(torch.cat([base + a * probes, base - a * probes]))
        return (pushed[:len(probes)] - pushed[len(probes):]) / (2 * a)

    def calibrate(self) -> np.ndarray:
        """``D`` ``(n_signals, K)``: the push-pull response to each actuator's influence function."""
        probes = torch.as_tensor(self.influence.T.toarray())
        return self.response(probes).T.numpy()

    def reconstruct(self, signals: torch.Tensor) -> torch.Tensor:
        """``R s``: ``(..., n_signals)`` signals to ``(..., K)`` commands (nm)."""
        s = torch.as_tensor(signals).to(torch.float64)
        require(s.ndim >= 1 and s.shape[-1] == self.n_signals,
                f"signals of shape {tuple(s.shape)} do not fit: the last dimension must be {self.n_signals}")
        return s @ torch.as_tensor(self.reconstructor, device=s.device).T

    def sense(self, phase_nm: torch.Tensor) -> torch.Tensor:
        """The sensor's noise-free view in command space, ``R s(phi)`` (nm)."""
        return self.reconstruct(self.signal(phase_nm))

    def photons_per_frame(self, magnitude: float, throughput: float, frame_period_s: float) -> float:
        """Photons from the guide star over the lit pupil in one frame: ``F0 10^(-0.4 mag) T A dt`` (``F0`` the
        band's zero point, photons / m² / s; ``A`` the pupil's area as sampled, m²)."""
        check_value("magnitude", magnitude, Interval(unit="magnitudes"))
        check_value("throughput", throughput, Interval(0, 1, closed="right", unit="fraction of the photons"))
        check_value("frame_period_s", frame_period_s, Interval(0, None, closed="neither", unit="s"))
        area = self.n_pupil * self.pupil_grid.pitch_m ** 2
        return PHOTOMETRY[self.config.band][2] * 10 ** (-0.4 * magnitude) * throughput * area * frame_period_s

    def measure(self, phase_nm: torch.Tensor, photons: float | None = None, read_noise_e: float = 0.0,
                generator: torch.Generator | None = None) -> torch.Tensor:
        """Signals ``(..., n_signals)`` of ``(..., n_pupil)`` OPD (nm) with photon noise (``photons`` per frame over
        the pupil; ``None``: noise-free) and Gaussian read noise (``read_noise_e`` electrons RMS per pixel), drawn
        from ``generator``."""
        frames = self.optics.frames(as_phase(phase_nm, self.n_pupil))
        if photons is not None:
            check_value("photons", photons, Interval(0, None, closed="neither", unit="photons per frame"))
            check_value("read_noise_e", read_noise_e, Interval(0, None, unit="electrons RMS per pixel"))
            frames = torch.poisson(frames * photons, generator=generator)
            if read_noise_e > 0:
                frames = frames + read_noise_e * torch.randn(frames.shape, generator=generator, dtype=frames.dtype)
        return self.signals.process(frames)

    def dm_surface(self, commands: torch.Tensor) -> torch.Tensor:
        """``IF y``: ``(..., K)`` commands (nm) to ``(..., n_pupil)`` DM surface (nm)."""
        y = torch.as_tensor(commands).to(torch.float64)
        require(y.shape[-1] == self.grid.n_actuators, f"commands of shape {tuple(y.shape)} do not fit: the last "
                                                      f"dimension must be {self.grid.n_actuators}")
        flat = y.reshape(-1, y.shape[-1]).cpu().numpy()
        return torch.as_tensor(np.asarray((self.influence @ flat.T).T)).reshape(*y.shape[:-1], self.n_pupil)

    def noise_propagation(self) -> float:
        """``trace(R R^T) / K``: mean command variance (nm²) per unit variance of white signal noise."""
        return float((self.reconstructor ** 2).sum() / self.grid.n_actuators)
