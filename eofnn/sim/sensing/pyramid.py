"""A diffractive modulated pyramid wavefront sensor: its optics, signals, noise, calibration and optical gains.

The pyramid is a four-faced glass prism at the focal plane: each face tilts the light that falls on it, so a relay
lens makes four images of the pupil on the detector, and the phase's gradients (or, unmodulated, the phase itself
above the PSF's core) become intensity differences between them. Everything is in torch, batched over frames,
on the device of the phase it is given (the calibration on the CPU in double precision by default).

- **Optics** (:class:`PyramidOptics`). The pupil is sampled on ``n = pixels_across * samples_per_pixel`` points
  across its diameter (pixel centres); its field ``exp(i 2 pi phi / lambda)`` (``phi`` the OPD in nm, ``lambda`` the
  sensing wavelength in nm) is zero-padded to ``N = 2 (pixels_across + separation) * samples_per_pixel`` points,
  Fourier transformed to the focal plane (sampled at ``N / n`` points per ``lambda / D``, the PSF centred between
  four points by a half-point tilt), multiplied by the pyramid's phase ``exp(-i (pi / 2) (|u| + |v|))`` (``u, v``
  focal-plane points from the vertex: each face shifts its light's pupil image by ``N / 4`` points along each axis)
  and transformed back: the four pupil images are centred in the four ``N / 2 x N / 2`` quadrants, each
  ``pixels_across`` detector pixels across with ``separation / 2`` pixels around it, after ``samples_per_pixel x
  samples_per_pixel`` binning. This is OOPAO's geometry (``OOPAO/Pyramid.py``: ``n_pix_separation``,
  ``n_pix_edge = n_pix_separation / 2``, ``psfCentering=True``, the rooftop-free mask of ``get_phase_mask``).
- **Modulation**: the detector integrates the frames of ``modulation_points`` tip-tilted fields whose PSF runs on a
  circle of radius ``modulation_lambda_over_d`` (``lambda / D``), starting on an edge of the pyramid; by default
  ``4 ceil(2 pi r / 4)`` points (OOPAO's ``nTheta``), one per ``lambda / D`` of circumference at least.
- **Flux**: the masks are unitary, so a frame holds every photon of the pupil (the frames here are fractions of the
  pupil's photons, summing to 1); photon noise (Poisson) and read noise (Gaussian, electrons per pixel) are drawn on
  the frame scaled to the photons per frame.
- **Signals** (``signal``). ``slopes_maps``: with ``I_1..I_4`` the four pupil images (``+x+y, -x+y, -x-y, +x-y``
  faces), ``s_x = (I_1 + I_4 - I_2 - I_3) / <I>``, ``s_y = (I_1 + I_2 - I_3 - I_4) / <I>`` on the valid pixels,
  ``<I>`` the mean of ``I_1 + I_2 + I_3 + I_4`` over them (OOPAO's ``slopesMaps``): a positive OPD gradient along x
  gives a positive ``s_x``, as the Shack-Hartmann's slopes. ``full_frame``: every valid detector pixel divided by
  their mean. The flat wavefront's signal is subtracted (the reference). Valid pixels: those where a frame taken with
  a large modulation (``calibration_modulation_lambda_over_d``, OOPAO's ``calibModulation``, capped at ``n / 2 - 1``)
  reaches ``light_ratio`` of its maximum (in the four images' sum for slopes maps, OOPAO's ``lightRatio``).
- **Calibration** (:class:`PyramidSensor`): the DM's Gaussian influence functions
  (:func:`~eofnn.sim.sensing.least_squares.influence_functions`) at the pupil's points, the interaction matrix
  ``D`` by push-pull of each actuator (``(s(+a IF_k) - s(-a IF_k)) / 2a``, ``a = push_pull_nm``) and the truncated
  least-squares reconstructor (:func:`~eofnn.sim.sensing.least_squares.least_squares_reconstructor`).
- **Optical gains** (:func:`optical_gains`): the pyramid is linear only about a flat wavefront; about a residual its
  response to a small probe of mode ``m`` is smaller (the residual smears the PSF over the faces as modulation does).
  Per mode, the gain is the projection of the response about the residual on the response about a flat wavefront,
  ``<D_res m, D_0 m> / <D_0 m, D_0 m>`` (the convolutional model's and the gain-sensing camera's quantity:
  Chambouleyron et al. 2020, A&A 644, A6; Fauvarque et al. 2019, JATIS 5, 1).

``tests/test_pyramid.py`` checks it against theory (linearity range against modulation, sensitivity against
spatial frequency, optical gains, flux, push-pull symmetry, noise), and ``experiments/pyramid/`` against OOPAO's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from eofnn.errors import require
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.sensing.detector import PHOTOMETRY
from eofnn.sim.sensing.least_squares import (
    MECHANICAL_COUPLING,
    default_relative_cut,
    influence_functions,
    least_squares_reconstructor,
)
from eofnn.validation import Constraint, Interval, OneOf, OrNone, check_value, validated

#: The pyramid's signals: slopes maps or the full frame.
SIGNALS = ("slopes_maps", "full_frame")
#: A batch of fields is propagated in chunks of about this many bytes of complex focal-plane arrays.
CHUNK_BYTES = 2 ** 25


def default_modulation_points(modulation_lambda_over_d: float) -> int:
    """OOPAO's number of modulation points, ``4 ceil(2 pi r / 4)`` (1 without modulation)."""
    if modulation_lambda_over_d == 0:
        return 1
    return 4 * math.ceil(2 * math.pi * modulation_lambda_over_d / 4)


class PyramidOptics:
    """The pyramid's optics on a sampled pupil: phase maps in, detector frames out (module docstring).

    Parameters
    ----------
    pupil : ndarray
        Boolean ``(n, n)`` pupil (row = y, column = x); ``n = pixels_across * samples_per_pixel``.
    pixels_across : int
        Detector pixels across each pupil image.
    samples_per_pixel : int
        Pupil points per detector pixel along each axis.
    separation_pixels : int
        Detector pixels between two pupil images (even: the images then fall on whole pixels).
    modulation_lambda_over_d : float
        Modulation radius (``lambda / D``).
    modulation_points : int or None
        Points on the modulation circle; ``None``: :func:`default_modulation_points`.
    wavelength_nm : float
        Sensing wavelength (nm): the phase of ``phi`` nm of OPD is ``2 pi phi / wavelength_nm``.
    """

    def __init__(self, pupil: np.ndarray, pixels_across: int, samples_per_pixel: int, separation_pixels: int,
                 modulation_lambda_over_d: float, modulation_points: int | None, wavelength_nm: float) -> None:
        pupil = np.asarray(pupil, dtype=bool)
        n = pixels_across * samples_per_pixel
        require(pupil.shape == (n, n), f"pupil of shape {pupil.shape} does not fit: expected ({n}, {n}) "
                                      f"({pixels_across} pixels x {samples_per_pixel} samples per pixel)")
        require(n % 2 == 0, f"pixels_across x samples_per_pixel = {n} is invalid: it must be even (the pupil is "
                            "centred between four focal-plane points)")
        require(separation_pixels % 2 == 0, f"separation_pixels={separation_pixels!r} is invalid: it must be even "
                                            "(the pupil images then fall on whole pixels)")
        check_value("modulation_lambda_over_d", modulation_lambda_over_d,
                    Interval(0, n / 2 - 1, unit=f"lambda / D; at most n / 2 - 1 on {n} pupil points across"))
        self.pupil, self.n = pupil, n
        self.pixels_across, self.samples_per_pixel, self.separation_pixels = pixels_across, samples_per_pixel, \
            separation_pixels
        self.n_padded = 2 * (pixels_across + separation_pixels) * samples_per_pixel
        self.detector_pixels = 2 * (pixels_across + separation_pixels)
        self.wavelength_nm = float(wavelength_nm)
        self.modulation_lambda_over_d = float(modulation_lambda_over_d)
        self.modulation_points = (default_modulation_points(modulation_lambda_over_d) if modulation_points is None
                                  else int(modulation_points))
        self.pupil_index = np.flatnonzero(pupil.ravel())
        self.n_pupil = len(self.pupil_index)
        self._cache: dict = {}

    @property
    def sampling(self) -> float:
        """Focal-plane points per ``lambda / D``, ``N / n``."""
        return self.n_padded / self.n

    def _arrays(self, device, complex_dtype) -> dict:
        key = (str(device), complex_dtype)
        if key not in self._cache:
            self._cache[key] = self._build_arrays(device, complex_dtype)
        return self._cache[key]

    def _build_arrays(self, device, complex_dtype) -> dict:
        n, big = self.n, self.n_padded
        real = torch.float64 if complex_dtype == torch.complex128 else torch.float32
        # Focal-plane coordinate of each unshifted FFT point (in points, half-integers): nu = k + 1/2, wrapped.
        k = np.arange(big)
        nu = np.where(k < big // 2, k + 0.5, k - big + 0.5)
        mask_phase = -(np.pi / 2) * (np.abs(nu)[None, :] + np.abs(nu)[:, None])
        # Half-point tilt of the padded pupil (the PSF then centred between four points) and the modulation's tilts,
        # on the pupil's n x n points (coordinates from the pupil's centre, in points).
        j = np.arange(n) - (n - 1) / 2
        half = np.exp(-1j * np.pi * (j[None, :] + j[:, None]) / big)
        r, k_mod = self.modulation_lambda_over_d, self.modulation_points
        theta = 2 * np.pi * np.arange(k_mod) / k_mod
        tilt = 2 * np.pi * r * (np.cos(theta)[:, None, None] * j[None, None, :]
                                + np.sin(theta)[:, None, None] * j[None, :, None]) / n
        phasors = half[None] * np.exp(1j * tilt) / math.sqrt(k_mod)
        return {"mask": torch.as_tensor(np.exp(1j * mask_phase), dtype=complex_dtype, device=device),
                "phasors": torch.as_tensor(phasors, dtype=complex_dtype, device=device),
                "half": torch.as_tensor(half[None], dtype=complex_dtype, device=device),
                "index": torch.as_tensor(self.pupil_index, device=device), "real": real}

    def frames(self, phase_nm: torch.Tensor, modulation: bool = True, single: bool = False) -> torch.Tensor:
        """Detector frames of ``(..., n_pupil)`` pupil OPD (nm; the pupil's points in row-major order):
        ``(..., P, P)`` fractions of the pupil's photons (each frame sums to 1), ``P = 2 (pixels_across +
        separation)``. ``modulation=False`` drops the modulation; ``single`` computes in complex64."""
        phase = torch.as_tensor(phase_nm)
        require(phase.ndim >= 1 and phase.shape[-1] == self.n_pupil,
                f"phase of shape {tuple(phase.shape)} does not fit: its last dimension must be {self.n_pupil} "
                "(the pupil's points)")
        complex_dtype = torch.complex64 if single else torch.complex128
        a = self._arrays(phase.device, complex_dtype)
        lead = phase.shape[:-1]
        flat = phase.reshape(-1, self.n_pupil).to(a["real"])
        phasors = a["phasors"] if modulation else a["half"]
        k_mod = phasors.shape[0]
        big, n, p, s = self.n_padded, self.n, self.detector_pixels, self.samples_per_pixel
        per_frame = k_mod * big * big * (16 if not single else 8) * 3
        step = max(1, CHUNK_BYTES // per_frame)
        out = torch.empty((flat.shape[0], p, p), dtype=a["real"], device=phase.device)
        offset = (big - n) // 2
        for start in range(0, flat.shape[0], step):
            chunk = flat[start:start + step]
            field = torch.zeros((chunk.shape[0], n * n), dtype=complex_dtype, device=phase.device)
            field[:, a["index"]] = torch.exp(1j * (2 * math.pi / self.wavelength_nm) * chunk).to(complex_dtype)
            field = field.reshape(-1, 1, n, n) * phasors[None]
            padded = torch.zeros((chunk.shape[0], k_mod, big, big), dtype=complex_dtype, device=phase.device)
            padded[..., offset:offset + n, offset:offset + n] = field
            focal = torch.fft.fft2(padded)
            focal *= a["mask"]
            image = torch.fft.ifft2(focal)
            intensity = torch.view_as_real(image).square().sum((-1, 1))
            out[start:start + step] = intensity.reshape(-1, p, s, p, s).sum((2, 4))
        return (out / self.n_pupil).reshape(*lead, p, p)

    def quadrants(self, frames: torch.Tensor) -> torch.Tensor:
        """The four pupil images ``(..., 4, pixels_across, pixels_across)`` of ``(..., P, P)`` frames, in the order
        of the faces ``+x+y, -x+y, -x-y, +x-y``."""
        half, e, m = self.detector_pixels // 2, self.separation_pixels // 2, self.pixels_across
        lo, hi = slice(e, e + m), slice(half + e, half + e + m)
        return torch.stack([frames[..., hi, hi], frames[..., hi, lo], frames[..., lo, lo], frames[..., lo, hi]], -3)


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

    _constraints: ClassVar[dict[str, Constraint]] = {
        "modulation_lambda_over_d": Interval(0, 255, unit="lambda / D"),
        "pixels_across": OrNone(Interval(2, 512, integer=True, unit="detector pixels across a pupil image")),
        "samples_per_pixel": Interval(1, 16, integer=True, unit="pupil points per detector pixel"),
        "separation_pixels": OneOf(tuple(range(0, 33, 2))),
        "modulation_points": OrNone(Interval(1, 10000, integer=True, unit="points on the modulation circle")),
        "light_ratio": Interval(0, 1, closed="left", unit="of the calibration frame's maximum"),
        "calibration_modulation_lambda_over_d": Interval(0, 1000, unit="lambda / D"),
        "signal": OneOf(SIGNALS),
        "band": OneOf(tuple(PHOTOMETRY)),
        "push_pull_nm": Interval(0, 100, closed="right", unit="nm of command"),
        "mechanical_coupling": Interval(0, 1, closed="neither", unit="influence at the neighbouring actuator"),
        "relative_cut": OrNone(Interval(1e-3, 1, unit="fraction of the largest singular value")),
        "pupil_diameter_m": OrNone(Interval(0, 100, closed="right", unit="m")),
    }

    @property
    def wavelength_nm(self) -> float:
        """The band's wavelength (nm)."""
        return PHOTOMETRY[self.band][0] * 1e9

    def build(self, grid: ActuatorGrid) -> PyramidSensor:
        """The sensor on ``grid``: optics, valid pixels, influence functions, ``D`` and ``R``."""
        return PyramidSensor(grid, self)


class PyramidSignals:
    """Valid pixels, reference and signal processing of a :class:`PyramidOptics` (module docstring).

    Parameters
    ----------
    optics : PyramidOptics
    signal : {"slopes_maps", "full_frame"}
    light_ratio : float
        Valid-pixel threshold, a fraction of the calibration frame's maximum.
    calibration_modulation_lambda_over_d : float
        Modulation of the frame that chooses the valid pixels (capped at ``n / 2 - 1``).
    valid : ndarray or None
        The valid pixels given (boolean, ``(pixels_across, pixels_across)`` for slopes maps, ``(P, P)`` for the full
        frame; OOPAO's ``userValidSignal``) instead of chosen by flux.
    """

    def __init__(self, optics: PyramidOptics, signal: str = "slopes_maps", light_ratio: float = 0.1,
                 calibration_modulation_lambda_over_d: float = 50.0, valid: np.ndarray | None = None) -> None:
        check_value("signal", signal, OneOf(SIGNALS))
        self.optics, self.signal = optics, signal
        side = optics.pixels_across if signal == "slopes_maps" else optics.detector_pixels
        if valid is not None:
            self.valid = np.asarray(valid, dtype=bool)
            require(self.valid.shape == (side, side) and self.valid.any(),
                    f"valid pixels of shape {self.valid.shape} do not fit: expected a ({side}, {side}) boolean map "
                    "with at least one pixel set")
        else:
            wide = min(calibration_modulation_lambda_over_d, optics.n / 2 - 1)
            calibration = PyramidOptics(optics.pupil, optics.pixels_across, optics.samples_per_pixel,
                                        optics.separation_pixels, wide, None, optics.wavelength_nm)
            frame = calibration.frames(torch.zeros(optics.n_pupil, dtype=torch.float64))
            image = optics.quadrants(frame).sum(0) if signal == "slopes_maps" else frame
            self.valid = (image >= light_ratio * image.max()).numpy()
        self.n_valid = int(self.valid.sum())
        self.n_signals = 2 * self.n_valid if signal == "slopes_maps" else self.n_valid
        self._valid = torch.as_tensor(self.valid)
        self.reference = self.process(optics.frames(torch.zeros(optics.n_pupil, dtype=torch.float64)),
                                      reference=False)

    def process(self, frames: torch.Tensor, reference: bool = True) -> torch.Tensor:
        """``(..., P, P)`` frames to ``(..., n_signals)`` signals, the reference subtracted unless ``reference`` is
        false."""
        valid = self._valid.to(frames.device)
        if self.signal == "slopes_maps":
            q = self.optics.quadrants(frames)[..., valid]  # (..., 4, n_valid)
            norm = q.sum(-2).mean(-1, keepdim=True)
            sx = (q[..., 0, :] + q[..., 3, :] - q[..., 1, :] - q[..., 2, :]) / norm
            sy = (q[..., 0, :] + q[..., 1, :] - q[..., 2, :] - q[..., 3, :]) / norm
            out = torch.cat([sx, sy], -1)
        else:
            pixels = frames[..., valid]
            out = pixels / pixels.mean(-1, keepdim=True)
        return out - self.reference.to(out) if reference else out


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
        self.pupil_grid = ActuatorGrid(pupil_m, n, grid.obstruction)
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
        return self.signals.process(self.optics.frames(_as_phase(phase_nm, self.n_pupil)))

    def response(self, probes_nm: torch.Tensor, around_nm: torch.Tensor | None = None,
                 amplitude_nm: float | None = None) -> torch.Tensor:
        """Push-pull response ``(M, n_signals)`` per nm of each of ``(M, n_pupil)`` probe shapes (nm per unit),
        about ``around_nm`` ``(n_pupil,)`` (a flat wavefront if ``None``): ``(s(r + a p) - s(r - a p)) / 2a``,
        ``a = amplitude_nm`` (the config's ``push_pull_nm`` if ``None``)."""
        a = self.config.push_pull_nm if amplitude_nm is None else amplitude_nm
        check_value("amplitude_nm", a, Interval(0, None, closed="neither", unit="nm"))
        probes = _as_phase(probes_nm, self.n_pupil).reshape(-1, self.n_pupil)
        base = torch.zeros(self.n_pupil, dtype=probes.dtype, device=probes.device) if around_nm is None else \
            _as_phase(around_nm, self.n_pupil).reshape(self.n_pupil).to(probes)
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
        frames = self.optics.frames(_as_phase(phase_nm, self.n_pupil))
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


def kl_modes(grid: ActuatorGrid, n_modes: int) -> np.ndarray:
    """``(K, n_modes)`` orthonormal command-space Karhunen-Loève modes of Kolmogorov turbulence on ``grid``'s
    actuators, piston removed, in decreasing variance: the eigenvectors of ``-P S P / 2`` (``S`` the structure
    function ``|x_i - x_j|^(5/3)`` between actuators, ``P`` the piston-removing projector)."""
    check_value("n_modes", n_modes, Interval(1, grid.n_actuators - 1, integer=True, unit="modes"))
    x = grid.positions_m
    structure = np.hypot(*(x[:, None, :] - x[None, :, :]).transpose(2, 0, 1)) ** (5 / 3)
    k = len(x)
    p = np.eye(k) - 1.0 / k
    values, vectors = np.linalg.eigh(-0.5 * p @ structure @ p)
    return vectors[:, np.argsort(values)[::-1][:n_modes]]


def optical_gains(sensor: PyramidSensor, modes_nm: torch.Tensor, residual_nm: torch.Tensor,
                  amplitude_nm: float | None = None) -> torch.Tensor:
    """Optical gains ``(R, M)`` of ``(M, n_pupil)`` mode shapes (nm per unit) about each of ``(R, n_pupil)``
    residual phases (nm): ``<D_res m, D_0 m> / <D_0 m, D_0 m>`` per mode (module docstring), the responses by
    push-pull of ``amplitude_nm`` (the config's ``push_pull_nm`` if ``None``)."""
    modes = _as_phase(modes_nm, sensor.n_pupil).reshape(-1, sensor.n_pupil)
    residuals = _as_phase(residual_nm, sensor.n_pupil).reshape(-1, sensor.n_pupil)
    flat = sensor.response(modes, None, amplitude_nm)
    norm = (flat * flat).sum(-1)
    require(bool((norm > 0).all()), "a mode the pyramid does not see (zero response about a flat wavefront) has no "
                                    "optical gain: remove it from modes_nm")
    gains = [(sensor.response(modes, r, amplitude_nm) * flat).sum(-1) / norm for r in residuals]
    return torch.stack(gains)


def modal_optical_gains(sensor: PyramidSensor, residual_nm: torch.Tensor, n_modes: int,
                        amplitude_nm: float | None = None) -> tuple[torch.Tensor, np.ndarray]:
    """Optical gains of the first ``n_modes`` Karhunen-Loève command modes (:func:`kl_modes`) measured on a loop's
    residual: ``(gains, modes)``, ``gains`` ``(n_modes,)`` the mean of :func:`optical_gains` over the ``(R,
    n_pupil)`` residual phases (nm; e.g. frames of a closed loop's residual over the pupil), ``modes`` the ``(K,
    n_modes)`` orthonormal command modes they belong to (a controller compensates mode ``m`` by dividing its
    reconstruction ``modes[:, m] . y`` by ``gains[m]``)."""
    modes = kl_modes(sensor.grid, n_modes)
    shapes = sensor.dm_surface(torch.as_tensor(modes.T))
    return optical_gains(sensor, shapes, residual_nm, amplitude_nm).mean(0), modes


def _as_phase(phase, n_pupil: int) -> torch.Tensor:
    phase = torch.as_tensor(phase)
    if not phase.is_floating_point():
        phase = phase.to(torch.float64)
    require(phase.ndim >= 1 and phase.shape[-1] == n_pupil, f"phase of shape {tuple(phase.shape)} does not fit: its "
                                                            f"last dimension must be {n_pupil} (the pupil's points)")
    return phase
