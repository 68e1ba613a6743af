"""Where OOPAO's diffractive Shack-Hartmann and eofnn's geometric one differ: slope noise, its propagation to the
pupil, and the turbulence each simulator draws (:mod:`eofnn.studies.sh_compare` compares the loops).

- **Slope calibration** (:func:`oopao_slope_units`): OOPAO's slopes are centroids in pixels (``wfs.signal``); a tilt
  of known OPD difference ``delta`` across a subaperture gives each slope's response ``k`` (signal per nm), so a
  slope of OOPAO is ``k`` times eofnn's slope unit (nm of OPD difference across the subaperture). OOPAO's
  interaction matrix, hence its reconstructor, is calibrated on the flat wavefront the same way.
- **Slope noise** (:func:`oopao_slope_noise`): photon noise on OOPAO's detector, in eofnn's unit (``noise / k``), on a
  flat wavefront and on the closed-loop residual (the same frame measured with and without noise), against eofnn's
  Rousset formula (:class:`~eofnn.sim.sensing.detector.Detector`).
- **Noise propagation** (:func:`eofnn_noise_propagation`, :func:`oopao_noise_propagation`): the piston-removed RMS
  over the pupil of ``IF R n`` per nm of white slope noise ``n``: what one reconstruction puts on the DM.
- **Turbulence** (:func:`structure_functions`): the phase structure function at lags of a pixel, a subaperture and
  four, in each simulator, against von Karman's.
"""

from __future__ import annotations

import math

import numpy as np

from eofnn.interop.loop import IntegratorControl
from eofnn.interop.oopao import quiet


def oopao_slope_units(sim, delta_nm: float = 10.0) -> np.ndarray:
    """``k`` ``(n_slopes,)``: OOPAO's slope response (signal per nm of OPD difference across a subaperture, along the
    slope's own axis) to a tilt on the flat wavefront, DM flat, no noise."""
    from OOPAO.OPD_map import OPD_map

    res = sim.tel.resolution
    x = (np.arange(res) - (res - 1) / 2) * sim.tel.D / res / (sim.tel.D / sim.settings["n_subapertures"])
    tilt_x = np.broadcast_to(x, (res, res))
    noise, sim.wfs.cam.photonNoise = sim.wfs.cam.photonNoise, False
    sim.dm.coefs = 0
    responses = []
    for tilt in (tilt_x, tilt_x.T):
        measured = []
        for sign in (1.0, -1.0):
            with quiet():
                sim.ngs ** sim.tel * OPD_map(sign * delta_nm * 1e-9 * tilt) * sim.wfs
            measured.append(sim.slopes().copy())
        responses.append((measured[0] - measured[1]) / (2 * delta_nm))
    sim.wfs.cam.photonNoise = noise
    half = len(responses[0]) // 2
    first = 0 if np.abs(responses[0][:half]).mean() > np.abs(responses[1][:half]).mean() else 1
    return np.concatenate([responses[first][:half], responses[1 - first][half:]])


def oopao_fully_lit(sim) -> np.ndarray:
    """Boolean ``(n_slopes,)``: the slopes of OOPAO's fully lit subapertures."""
    flux = np.asarray(sim.wfs.photon_per_subaperture).ravel()
    valid = np.asarray(sim.wfs.valid_subapertures_1D, dtype=bool)
    lit = flux[valid] >= (1 - 1e-6) * flux.max()
    return np.concatenate([lit, lit])


def oopao_slope_noise(sim, gain: float, n_frames: int, seed: int, *, settle_frames: int = 100, every: int = 10,
                      flat_frames: int = 100) -> dict:
    """Photon noise per slope of ``sim`` (OOPAO's SH with photon noise) in nm of OPD difference across a
    subaperture: ``{"flat_nm", "loop_nm"}`` (RMS over the fully lit slopes; ``*_all_nm`` over every slope), and the
    open-loop noise it puts on the pupil through the reconstructor (``flat_pupil_nm``, ``loop_pupil_nm``: the
    piston-removed RMS over the pupil of the DM shape ``R n`` commands).

    Flat: ``flat_frames`` frames of a flat wavefront. Loop: the integrator of ``gain`` closes ``sim``'s loop on the
    realisation ``seed``; every ``every`` frames after ``settle_frames`` the frame's residual is measured again
    without and with noise."""
    k = oopao_slope_units(sim)
    lit = oopao_fully_lit(sim)
    modes = np.asarray(sim.dm.modes)[sim._pupil.ravel()].astype(np.float64)
    sim.dm.coefs = 0
    sim.wfs.cam.photonNoise = True
    flat, pupil = [], []
    with quiet():
        sim.ngs ** sim.tel * sim.wfs
    clean = _measure(sim, False)
    for _ in range(flat_frames):
        n = _measure(sim, True) - clean
        flat.append(n / k)
        surface = modes @ (sim.reconstructor @ n)
        pupil.append(np.std(surface))
    control = IntegratorControl(gain)
    sim.reset(seed)
    control.reset(sim.n_actuators)
    pending, loop, loop_pupil = [np.zeros(sim.n_actuators) for _ in range(sim.delay_frames)], [], []
    for frame in range(n_frames):
        command = sim.project(control.step(pending.pop(0)))
        measurement, _ = sim.advance(command)
        pending.append(measurement)
        if frame >= settle_frames and frame % every == 0:
            clean = _measure(sim, False, dm=True)
            n = _measure(sim, True, dm=True) - clean
            loop.append(n / k)
            loop_pupil.append(np.std(modes @ (sim.reconstructor @ n)))
    sim.wfs.cam.photonNoise = sim.photon_noise
    flat, loop = np.asarray(flat), np.asarray(loop)
    rms = lambda a, m: float(np.sqrt(np.mean(a[:, m] ** 2)))  # noqa: E731
    every_slope = np.ones_like(lit)
    return {"flat_nm": rms(flat, lit), "loop_nm": rms(loop, lit), "flat_all_nm": rms(flat, every_slope),
            "loop_all_nm": rms(loop, every_slope), "flat_pupil_nm": float(np.sqrt(np.mean(np.square(pupil)))),
            "loop_pupil_nm": float(np.sqrt(np.mean(np.square(loop_pupil)))),
            "units_per_nm": float(np.median(np.abs(k[lit]))), "n_loop_probes": len(loop),
            "photons_per_subaperture": float(np.asarray(sim.wfs.photon_per_subaperture).max())}


def _measure(sim, noise: bool, dm: bool = False) -> np.ndarray:
    """The SH's slopes of the light as it stands (through the DM if ``dm``), with or without photon noise."""
    sim.wfs.cam.photonNoise = noise
    if dm:
        sim._restart_light()  # ``*`` alone would add the DM to what is there
    with quiet():
        if dm:
            sim.ngs * sim.tel * sim.dm * sim.wfs
        else:
            sim.ngs * sim.tel * sim.wfs
    return sim.slopes().copy()


def _piston_free_rms(matrix: np.ndarray) -> float:
    """RMS over the rows (pupil points) of ``matrix @ n`` for white unit ``n``, piston removed."""
    centred = matrix - matrix.mean(0)
    return float(math.sqrt((centred ** 2).sum() / len(matrix)))


def eofnn_noise_propagation(scenario) -> float:
    """Piston-removed RMS over eofnn's pupil of ``IF R n`` per nm RMS of white slope noise ``n`` (nm / nm)."""
    from eofnn.sim.loop.sensing import loop_operators

    ops = loop_operators(scenario.grid, scenario.sensor.shack_hartmann())
    influence = ops.influence_pupil_t.T.toarray()  # (N_p, K), nm of surface per nm of command
    return _piston_free_rms(influence @ ops.reconstructor.numpy())


def oopao_noise_propagation(sim, units_per_nm: np.ndarray) -> float:
    """The same for OOPAO: its reconstructor on slopes in eofnn's unit (``units_per_nm``: :func:`oopao_slope_units`)."""
    modes = np.asarray(sim.dm.modes)[sim._pupil.ravel()].astype(np.float64)
    return _piston_free_rms(modes @ (sim.reconstructor * units_per_nm))


def von_karman_structure_function(r_m: np.ndarray, r0_m: float, outer_scale_m: float,
                                  wavelength_m: float = 500e-9) -> np.ndarray:
    """Von Karman's phase structure function ``D(r)`` as OPD (nm²), r0 at ``wavelength_m``."""
    from scipy.special import gamma, kv

    # The phase covariance B(r) = c u^(5/6) K_5/6(u), u = 2 pi r / L0 (Conan 2000; aotools' phase_covariance), whose
    # limit at r = 0 is the variance 0.0863 (L0 / r0)^(5/3) rad², and D(r) = 2 (B(0) - B(r)) -> 6.88 (r / r0)^(5/3)
    # for r << L0.
    c = (outer_scale_m / r0_m) ** (5 / 3) * 2 ** (-5 / 6) * gamma(11 / 6) / math.pi ** (8 / 3) \
        * (24 / 5 * gamma(6 / 5)) ** (5 / 6)
    u = 2 * math.pi * np.asarray(r_m, dtype=np.float64) / outer_scale_m
    covariance0 = c * gamma(5 / 6) * 2 ** (-1 / 6)
    covariance = c * u ** (5 / 6) * kv(5 / 6, u)
    return 2 * (covariance0 - covariance) * (wavelength_m * 1e9 / (2 * math.pi)) ** 2


def _structure(maps: np.ndarray, lags) -> list[float]:
    """Mean squared difference (nm²) of ``(frames, n, n)`` maps (NaN outside) at ``lags`` pixels along both axes."""
    out = []
    for lag in lags:
        diffs = [maps[:, :, lag:] - maps[:, :, :-lag], maps[:, lag:, :] - maps[:, :-lag, :]]
        out.append(float(np.mean(np.concatenate([d[np.isfinite(d)] for d in diffs]) ** 2)))
    return out


def structure_functions(system, seeds, n_frames: int, every: int = 20) -> dict:
    """The phase structure function (nm²) at lags of one pixel, one subaperture and four, of eofnn's turbulence
    (the SH's fine grid), OOPAO's atmosphere (its pupil) and von Karman's, over every ``every``-th of ``n_frames``
    frames of each of ``seeds``."""
    m = system.samples_per_subaperture
    lags = (1, m, 4 * m)
    scenario = system.eofnn_scenario(None, n_frames)
    eofnn_maps, oopao_maps = [], []
    for seed in seeds:
        turbulence = scenario.turbulence(int(seed), "test", 1)
        grid = turbulence.fine_grid
        eofnn_maps.append(grid.to_map(turbulence.fine.frames(0, n_frames)[0, ::every]).numpy())
    sim = system.oopao("perfect")
    for seed in seeds:
        sim.reset(int(seed))
        for frame in range(n_frames):
            sim.step_turbulence()
            if frame % every == 0:
                oopao_maps.append(np.where(sim._pupil, np.asarray(sim.atm.OPD) * 1e9, np.nan))
    pixel = system.pitch_m / m
    return {"lags_m": [lag * pixel for lag in lags],
            "eofnn_nm2": _structure(np.concatenate(eofnn_maps), lags),
            "oopao_nm2": _structure(np.asarray(oopao_maps), lags),
            "von_karman_nm2": von_karman_structure_function(np.asarray(lags) * pixel, system.r0_m,
                                                            system.outer_scale_m).tolist()}


def eofnn_fit_over_disc(scenario, seed: int, realisations: int, n_frames: int, settle_frames: int,
                        diameter_m: float, every: int = 10) -> list[float]:
    """eofnn's fitting error if its pupil were the disc of ``diameter_m`` (OOPAO's): the phase there minus its
    least-squares fit by eofnn's DM on the modes its sensor sees, fitted over that disc alone; the median
    piston-removed RMS (nm) of each realisation over every ``every``-th frame after ``settle_frames``."""
    turbulence = scenario.turbulence(seed, "test", realisations)
    ops = turbulence.operators
    radius = np.hypot(*ops.sensor.geometry.fine_positions_m.T)
    inside = radius <= diameter_m / 2 * (1 + 1e-9)
    influence = (ops.sensor.influence / ops.surface_per_command).tocsr()[inside].toarray()
    values, vectors = np.linalg.eigh(ops.projector.numpy())  # P = V_k V_k^T: the seen command modes
    basis = influence @ vectors[:, values > 0.5]
    basis = np.concatenate([basis, np.ones((len(basis), 1))], 1)  # piston is free: the residual's is removed
    phase = turbulence.fine.frames(settle_frames, n_frames)[:, ::every].numpy()[..., inside]  # (R, t, points)
    flat = phase.reshape(-1, phase.shape[-1])
    residual = flat - (basis @ np.linalg.lstsq(basis, flat.T, rcond=None)[0]).T
    residual -= residual.mean(-1, keepdims=True)
    rms = np.sqrt((residual ** 2).mean(-1)).reshape(phase.shape[:2])
    return [float(np.median(r)) for r in rms]
