"""OOPAO's modulated pyramid in the OOPAO adapter (:class:`eofnn.interop.oopao.OopaoLoop` with ``sensor="pyramid"``).

The sensor is ``OOPAO.Pyramid`` built as OOPAO's tutorials build it: ``nSubap`` detector pixels across each pupil
image (one per subaperture of the Fried DM, so ``pupil_pixels_per_subaperture`` pupil points per pixel), the
modulation radius in ``lambda / D`` at the guide star's wavelength (I band) on OOPAO's default points
(``4 ceil(2 pi r / 4)``), two pixels between the images, the PSF centred on four pixels, pixels valid where a frame
modulated by 50 ``lambda / D`` reaches :data:`LIGHT_RATIO` of its maximum, and slopes maps normalised by the mean
flux of the four images (``postProcessing="slopesMaps"``: eofnn's ``signal: slopes_maps``). The loop reconstructs
with the truncated pseudo-inverse of OOPAO's push-pull interaction matrix as for the Shack-Hartmann.

About a closed-loop residual the pyramid responds less than about a flat wavefront (its optical gains):
:func:`probe_optical_gains` measures them on OOPAO's pyramid by the method of eofnn's
:func:`eofnn.sim.sensing.optical_gains.optical_gains` (push-pull of each mode's DM surface about the residual,
projected on its push-pull about a flat wavefront).
"""

from __future__ import annotations

import contextlib
import io

import numpy as np

#: OOPAO's ``lightRatio`` of the pyramid's valid pixels (its tutorials' value, eofnn's ``light_ratio`` default).
LIGHT_RATIO = 0.1
#: Pixels between the pupil images on the detector (OOPAO's ``n_pix_separation``, eofnn's ``separation_pixels``).
SEPARATION_PIXELS = 2


def build_pyramid(pyramid_class, tel, n_subapertures: int, modulation_lambda_over_d: float):
    """OOPAO's ``Pyramid`` of ``n_subapertures`` pixels across each pupil image on ``tel`` (module docstring)."""
    return pyramid_class(nSubap=n_subapertures, telescope=tel, modulation=modulation_lambda_over_d,
                         lightRatio=LIGHT_RATIO, n_pix_separation=SEPARATION_PIXELS, psfCentering=True,
                         postProcessing="slopesMaps")


def pyramid_signals(wfs, phase_rad: np.ndarray) -> np.ndarray:
    """OOPAO's pyramid signals ``(M, nSignal)`` of ``(M, n, n)`` phase maps (rad), without touching the telescope's
    light (``wfs_measure`` on the phase alone; the detector's noise as it is set)."""
    phase = np.ascontiguousarray(np.moveaxis(np.asarray(phase_rad, dtype=np.float64), 0, -1))
    with contextlib.redirect_stdout(io.StringIO()):  # OOPAO's prints (as the adapter's ``quiet``)
        wfs.wfs_measure(phase_in=phase)
    signal = np.asarray(wfs.signal, dtype=np.float64)
    return signal.T if signal.ndim == 2 else signal[None]


def probe_optical_gains(sim, commands: np.ndarray, residuals_nm: np.ndarray, amplitude_nm: float = 1.0) -> np.ndarray:
    """Optical gains ``(R, M)`` of OOPAO's pyramid in ``sim`` (an ``OopaoLoop`` with ``sensor="pyramid"``) for the
    DM surfaces of ``(K, M)`` commands (nm of command per unit, e.g. orthonormal command modes) about each of ``(R,
    n, n)`` residual OPD maps (nm, on the telescope's pixels): ``<D_res m, D_0 m> / <D_0 m, D_0 m>`` per mode, the
    responses by push-pull of ``amplitude_nm`` (the method of eofnn's ``optical_gains``)."""
    wavelength_nm = float(sim.ngs.wavelength) * 1e9
    res = sim.tel.resolution
    influence = np.asarray(sim.dm.modes, dtype=np.float64)  # (res * res, K): peak 1 per unit of coefficient
    shapes = (influence @ np.asarray(commands, dtype=np.float64)).T.reshape(-1, res, res)  # nm per unit
    shapes *= np.asarray(sim.tel.pupil, dtype=np.float64)
    to_rad = 2 * np.pi / wavelength_nm
    noise, sim.wfs.cam.photonNoise = sim.wfs.cam.photonNoise, False

    def response(around_nm):
        push = np.concatenate([around_nm + amplitude_nm * shapes, around_nm - amplitude_nm * shapes])
        signals = pyramid_signals(sim.wfs, push * to_rad)
        return (signals[:len(shapes)] - signals[len(shapes):]) / (2 * amplitude_nm)

    try:
        flat = response(np.zeros((res, res)))
        norm = (flat * flat).sum(1)
        gains = [(response(np.asarray(r, dtype=np.float64)) * flat).sum(1) / norm for r in residuals_nm]
    finally:
        sim.wfs.cam.photonNoise = noise
    return np.asarray(gains)


def gain_sensing_camera_gains(sim, commands: np.ndarray, residuals_nm: np.ndarray) -> np.ndarray:
    """Optical gains ``(R, M)`` of the same modes by OOPAO's ``GainSensingCamera`` (the convolutional model of
    Chambouleyron et al. 2021 on the modulated focal-plane image, not a push-pull): calibrated on the focal plane
    about a flat wavefront, then read about each residual map (nm), as OOPAO's docstring does it, the light given
    to the pyramid as a phase (``wfs_measure``)."""
    from OOPAO.GainSensingCamera import GainSensingCamera

    wfs, res = sim.wfs, sim.tel.resolution
    to_rad = 2 * np.pi / (float(sim.ngs.wavelength) * 1e9)
    influence = np.asarray(sim.dm.modes, dtype=np.float64)
    basis = (influence @ np.asarray(commands, dtype=np.float64)).reshape(res, res, -1)
    basis *= np.asarray(sim.tel.pupil, dtype=np.float64)[..., None]
    noise, wfs.cam.photonNoise = wfs.cam.photonNoise, False
    gains = []
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            wfs.compute_focal_plane = True
            wfs.focal_plane_camera.resolution = wfs.nRes
            camera = GainSensingCamera(wfs.mask, basis, n_jobs=1)
            for phase in [np.zeros((res, res)), *(np.asarray(r, dtype=np.float64) * to_rad for r in residuals_nm)]:
                wfs.wfs_measure(phase_in=phase)
                wfs * wfs.focal_plane_camera
                wfs.focal_plane_camera * camera  # the first: its calibration
                gains.append(np.array(camera.og, dtype=np.float64))
    finally:
        wfs.cam.photonNoise = noise
    return np.asarray(gains[1:])
