"""A diffractive modulated pyramid's optics and signals: phase maps in, detector frames out, signals from them.

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
The sensor that calibrates and reconstructs from them: :mod:`eofnn.sim.sensing.pyramid`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from eofnn.errors import require
from eofnn.sim.sensing.constants import PYRAMID_SIGNALS as SIGNALS
from eofnn.validation import Interval, OneOf, check_value

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


def as_phase(phase, n_pupil: int) -> torch.Tensor:
    """``phase`` as a floating tensor whose last dimension is the ``n_pupil`` pupil points (one line otherwise)."""
    phase = torch.as_tensor(phase)
    if not phase.is_floating_point():
        phase = phase.to(torch.float64)
    require(phase.ndim >= 1 and phase.shape[-1] == n_pupil, f"phase of shape {tuple(phase.shape)} does not fit: its "
                                                            f"last dimension must be {n_pupil} (the pupil's points)")
    return phase
