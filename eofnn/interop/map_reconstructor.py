"""A noise-aware (MAP / MMSE) reconstructor for an OOPAO loop, in place of the truncated least-squares one.

``R = V (D_m^T C_n^-1 D_m + w C_m^-1)^-1 D_m^T C_n^-1`` ``(K, n_slopes)``, with ``D`` OOPAO's interaction matrix
(slopes per nm of command, as :class:`eofnn.interop.oopao.OopaoLoop` measures it), ``V`` the loop's controlled
command modes (``sim.controlled_modes``, the modes ``rcond`` keeps: the same space as the least-squares
reconstructor's, so only the weighting differs), ``D_m = D V``, ``C_m = V^T C_phi V`` with ``C_phi`` the actuator-space
covariance of von Kármán turbulence fitted by the DM (``F C_pix F^T``, ``F`` the adapter's own least-squares fit of a
piston-free phase, the fit its truth ``turbulence_fit_nm`` is), ``C_n`` the slope noise covariance (diagonal) and
``w`` one regularisation factor (1: the prior as estimated). ``w = 0`` with white noise is the least-squares
reconstructor exactly. The phase covariance ``C_pix`` between the pupil's pixels is von Kármán's
(:func:`eofnn.sim.sensing.mmse.von_karman_covariance_nm2`, the formula eofnn's own MMSE reconstructor uses), applied
by FFT convolution (it depends only on the offset), with ``B(0)`` subtracted (``F`` removes piston, so only the
structure function matters).

Two variants (:func:`apply_reconstructor`):

- ``map``: ``C_phi`` from the simulator's ``r0`` and ``L0`` and ``C_n`` from OOPAO's photon noise read on the
  simulator's own frames (the detector read again and again on the same frame, against its noise-free read):
  simulator knowledge, labelled so;
- ``map_telemetry``: both from a recording of the loop's own integrator (slopes and applied commands, on the scan
  realisation): the gain the commands reach the slopes with (DM gain x optical gain) by least squares on second
  temporal differences, ``C_n`` from the second temporal difference of the pseudo-open-loop slopes (white noise gives
  ``6 sigma^2``, the frozen-flow signal almost nothing), ``r0`` and ``L0`` by fitting the von Kármán model's
  modal variances to the pseudo-open-loop modal variances less their noise. No simulator setting is read.

``w`` is chosen by the loop itself: each factor of ``weights`` closes the best-gain integrator's loop on the scan
realisation (never a scored one) and the lowest median residual wins.
"""

from __future__ import annotations

import numpy as np

from eofnn.errors import ConfigError, require
from eofnn.sim.sensing.mmse import NOISE_FLOOR, von_karman_covariance_nm2

RECONSTRUCTORS = ("least_squares", "map", "map_telemetry")
#: The regularisation factors scanned on the scan realisation.
WEIGHTS = (0.25, 1.0, 4.0)
#: The outer scales (m) the telemetry variant tries.
OUTER_SCALES_M = (10.0, 25.0, 100.0)
#: r0's wavelength in OOPAO (500 nm).
R0_WAVELENGTH_M = 500e-9


def map_reconstructor(interaction_matrix, modes, prior_nm2, noise_var, weight: float = 1.0) -> np.ndarray:
    """``R = V (D_m^T W D_m + w C_m^-1)^-1 D_m^T W`` ``(K, S)``, ``W = C_n^-1`` (module docstring).

    ``interaction_matrix`` ``(S, K)``; ``modes`` ``V`` ``(K, m)`` orthonormal; ``prior_nm2`` ``C_phi`` ``(K, K)``;
    ``noise_var`` the slope noise variance: a number, ``(S,)`` per slope or ``(S, S)`` (floored at
    :data:`~eofnn.sim.sensing.mmse.NOISE_FLOOR` of the mean noise-free slope variance, as eofnn's MMSE is);
    ``weight`` ``w >= 0``. Solved as ``(C_m D_m^T W D_m + w I)^-1 C_m D_m^T W``: ``C_m`` is never inverted.
    """
    d = np.asarray(interaction_matrix, dtype=np.float64)
    v = np.asarray(modes, dtype=np.float64)
    c = np.asarray(prior_nm2, dtype=np.float64)
    require(d.ndim == 2, f"interaction_matrix of shape {d.shape} is invalid: (n_slopes, n_actuators)")
    s, k = d.shape
    require(v.ndim == 2 and v.shape[0] == k and 0 < v.shape[1] <= min(k, s),
            f"modes of shape {v.shape} is invalid: ({k}, m) with 0 < m <= {min(k, s)} for a {d.shape} interaction matrix")
    require(c.shape == (k, k), f"prior_nm2 of shape {c.shape} is invalid: ({k}, {k}) for {k} actuators")
    require(np.isfinite(weight) and weight >= 0, f"weight={weight!r} is invalid: a number >= 0")
    dm, cm = d @ v, v.T @ c @ v
    cm = 0.5 * (cm + cm.T)
    floor = NOISE_FLOOR * max(float(np.trace(dm @ cm @ dm.T)) / s, 1e-300)
    n = np.asarray(noise_var, dtype=np.float64)
    if n.ndim == 0:
        n = np.full(s, float(n))
    if n.ndim == 1:
        require(n.shape == (s,), f"noise_var of shape {n.shape} is invalid: a number, ({s},) or ({s}, {s})")
        require(bool(np.all(n >= 0)), "noise_var is invalid: variances must be >= 0")
        dtw = dm.T / np.maximum(n, floor)  # D_m^T W, W diagonal
    else:
        require(n.shape == (s, s), f"noise_var of shape {n.shape} is invalid: a number, ({s},) or ({s}, {s})")
        n = 0.5 * (n + n.T) + floor * np.eye(s)
        dtw = np.linalg.solve(n, dm).T
    a = cm @ (dtw @ dm) + weight * np.eye(len(cm))
    return v @ np.linalg.solve(a, cm @ dtw)


def fitted_prior_nm2(fit: np.ndarray, pupil: np.ndarray, pixel_m: float, r0_m: float, outer_scale_m: float,
                     wavelength_m: float = R0_WAVELENGTH_M, chunk: int = 64) -> np.ndarray:
    """``F C_pix F^T`` ``(K, K)`` (nm² of command): von Kármán's covariance of the DM's fit ``F`` ``(K, N_p)`` of a
    piston-free phase on the ``pupil`` ``(n, n)`` bool pixels of pitch ``pixel_m``; ``F`` must remove piston
    (``F @ 1 = 0``), so ``B(r) - B(0)`` is used."""
    fit = np.asarray(fit, dtype=np.float64)
    pupil = np.asarray(pupil, dtype=bool)
    require(pupil.ndim == 2 and fit.ndim == 2 and fit.shape[1] == int(pupil.sum()),
            f"fit of shape {fit.shape} is invalid: (K, {int(pupil.sum())}), one column per pupil pixel")
    n = pupil.shape[0]
    i = np.arange(-(n - 1), n)
    r = np.hypot(*np.meshgrid(i, i, indexing="ij")) * pixel_m
    table = von_karman_covariance_nm2(r, r0_m, outer_scale_m, wavelength_m)
    table = table - table[n - 1, n - 1]  # B(r) - B(0): F removes piston
    shape = (3 * n - 2, 3 * n - 2)  # the full linear convolution: no wrap
    kernel = np.fft.rfft2(table, s=shape)
    out = np.zeros((len(fit), len(fit)))
    for lo in range(0, len(fit), chunk):
        rows = fit[lo:lo + chunk]
        images = np.zeros((len(rows), n, n))
        images[:, pupil] = rows
        conv = np.fft.irfft2(np.fft.rfft2(images, s=shape) * kernel, s=shape)
        conv = conv[:, n - 1:2 * n - 1, n - 1:2 * n - 1]  # (C_pix f)(x) at the n x n pixels
        out[lo:lo + chunk] = conv[:, pupil] @ fit.T
    return 0.5 * (out + out.T)


def sim_prior_nm2(sim, r0_m: float, outer_scale_m: float) -> np.ndarray:
    """:func:`fitted_prior_nm2` for an :class:`~eofnn.interop.oopao.OopaoLoop`: its fit operator and pupil."""
    fit = sim._fit_operator()[1]
    pupil = sim.pupil_mask
    return fitted_prior_nm2(fit, pupil, sim.settings["diameter_m"] / pupil.shape[0], r0_m, outer_scale_m)


def _slopes_and_commanded(slopes, commands, interaction_matrix) -> tuple[np.ndarray, np.ndarray]:
    """``(s, D c)`` ``(T, S)`` each: the slopes and what the commands put on them, their shapes checked."""
    s, c = np.asarray(slopes, dtype=np.float64), np.asarray(commands, dtype=np.float64)
    d = np.asarray(interaction_matrix, dtype=np.float64)
    require(s.ndim == 2 and c.ndim == 2 and len(s) == len(c) and s.shape[1] == d.shape[0] and c.shape[1] == d.shape[1],
            f"slopes {s.shape} and commands {c.shape} are invalid for a {d.shape} interaction matrix: (T, "
            f"{d.shape[0]}) and (T, {d.shape[1]})")
    return s, c @ d.T


def pseudo_open_loop_slopes(slopes, commands, interaction_matrix, dm_gain: float = 1.0) -> np.ndarray:
    """``p(n) = s(n) - g D c(n)`` ``(T, S)``: the slopes of frame ``n`` less what the command applied at that frame
    (``c(n)``, the DM set before the sensor read) put on them (OOPAO's slopes are of the turbulence plus the DM)."""
    s, dc = _slopes_and_commanded(slopes, commands, interaction_matrix)
    return s - dm_gain * dc


def dm_gain_from_slopes(slopes, commands, interaction_matrix) -> float:
    """The gain ``g`` with which the applied commands reach the slopes (the DM's gain times the sensor's optical
    gain), by least squares on second temporal differences: ``D2 s = g D2 (D c) + ...``; the dither and the loop's
    noise make ``D2 c`` rich, while the turbulence's slopes barely change and the slope noise of a frame is not in
    that frame's command (the loop's delay)."""
    s, dc = _slopes_and_commanded(slopes, commands, interaction_matrix)
    s2, dc2 = (x[2:] - 2 * x[1:-1] + x[:-2] for x in (s, dc))
    energy = float(np.sum(dc2 * dc2))
    require(energy > 0, "the commands never change: a recording with dither is needed to tell the DM's gain")
    return float(np.sum(s2 * dc2) / energy)


def slope_noise_from_pol(pol: np.ndarray) -> np.ndarray:
    """Each slope's white noise variance ``(S,)`` from pseudo-open-loop slopes ``(T, S)``: the variance of the second
    temporal difference over 6 (white noise: ``(1 + 4 + 1) sigma^2``; a smooth signal: almost nothing)."""
    pol = np.asarray(pol, dtype=np.float64)
    require(pol.ndim == 2 and len(pol) >= 10, f"pseudo-open-loop slopes of shape {pol.shape} are invalid: (T >= 10, S)")
    second = pol[2:] - 2 * pol[1:-1] + pol[:-2]
    return second.var(0) / 6


def fit_turbulence(pol: np.ndarray, noise_var: np.ndarray, interaction_matrix, modes, priors: dict) -> dict:
    """``r0`` and ``L0`` from pseudo-open-loop slopes: the modal variances of ``pinv(D V) p`` less their noise against
    each ``priors[L0]`` (``C_phi`` at ``r0 = 1`` m) in log, a scale (``r0^(-5/3)``) each; the best ``L0`` wins.
    Returns ``{"r0_m", "outer_scale_m", "log_misfit", "modes_used"}``."""
    dm = np.asarray(interaction_matrix, dtype=np.float64) @ modes
    pinv = np.linalg.pinv(dm)
    measured = (pol @ pinv.T).var(0) - np.einsum("ij,j,ij->i", pinv, noise_var, pinv)
    fits = {}
    for outer, prior in priors.items():
        model = np.einsum("ki,kl,li->i", modes, prior, modes)
        ok = (measured > 0) & (model > 0)
        require(ok.sum() >= 3, "the recording gives fewer than 3 modes above their noise: record longer or brighter")
        ratio = np.log(measured[ok] / model[ok])
        scale = float(np.median(ratio))
        fits[outer] = {"r0_m": float(np.exp(-0.6 * scale)), "outer_scale_m": float(outer),
                       "log_misfit": float(np.median(np.abs(ratio - scale))), "modes_used": int(ok.sum())}
    return min(fits.values(), key=lambda f: f["log_misfit"])


def simulator_slope_noise(sim, n_frames: int = 10, reads: int = 20, seed: int = 9000) -> np.ndarray:
    """OOPAO's photon noise per slope ``(S,)`` (simulator knowledge): on ``n_frames`` frames of the realisation
    ``seed`` (the DM on the turbulence's fit, as a closed loop leaves a fitting residual), the detector read
    ``reads`` times with noise against its noise-free read."""
    if not sim.photon_noise:
        return np.zeros(sim.interaction_matrix.shape[0])
    from eofnn.interop.oopao import quiet

    sim.reset(seed)
    camera, deviations = sim.wfs.cam, []
    try:
        for _ in range(n_frames):
            for _ in range(10):
                sim.step_turbulence()
            surface = -sim.turbulence_fit_nm() * 1e-9  # the DM's coefficients that cancel the fit
            reads_ = []
            for noisy in [False] + [True] * reads:
                camera.photonNoise = noisy
                sim._restart_light()
                with quiet():
                    sim.dm.coefs = surface
                    sim.ngs * sim.tel * sim.dm * sim.wfs
                reads_.append(sim.slopes())
            deviations.append(np.asarray(reads_[1:]) - reads_[0])
    finally:
        camera.photonNoise = sim.photon_noise
    return np.mean(np.concatenate(deviations) ** 2, axis=0)


def record_loop(sim, gain: float, n_frames: int, seed: int, dither_nm: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """``(slopes, commands)`` ``(T, S)``, ``(T, K)`` of ``sim``'s dithered integrator loop on realisation ``seed``."""
    from eofnn.interop.loop import IntegratorControl, require_recorded, run_closed_loop

    slopes = []
    record = run_closed_loop(sim, IntegratorControl(gain, dither_nm, seed + 300), n_frames, seed,
                             observers=[lambda n, s: slopes.append(s.slopes())])
    require_recorded(record, gain, sim)
    return np.asarray(slopes), record.y


def apply_reconstructor(sim, kind: str, *, scan_seed: int, loop_frames: int, settle_frames: int, gains,
                        record_frames: int = 2000, record_gain: float = 0.3, weights=WEIGHTS,
                        progress=print) -> dict:
    """Replace ``sim.reconstructor`` (the least-squares one) by the ``kind`` reconstructor (module docstring), its
    factor ``w`` chosen among ``weights`` on the realisation ``scan_seed``; returns what was estimated and scanned
    (JSON-ready). ``least_squares`` leaves the loop as it is."""
    if kind not in RECONSTRUCTORS:
        raise ConfigError(f"reconstructor={kind!r} is invalid: one of {', '.join(RECONSTRUCTORS)}")
    if kind == "least_squares":
        return {"kind": kind}
    require(getattr(sim, "sensor", None) != "perfect", f"reconstructor={kind!r} is invalid with the perfect sensor: "
            "it has no slopes")
    from eofnn.interop.loop import scan_integrator

    d, v = sim.interaction_matrix, sim.controlled_modes
    least_squares = sim.reconstructor
    if kind == "map":
        r0, outer = sim.settings["r0_m"], sim.settings["outer_scale_m"]
        noise = simulator_slope_noise(sim)
        prior = sim_prior_nm2(sim, r0, outer)
        info = {"kind": kind, "knowledge": "simulator: r0 and L0 from its settings, the slope noise from its detector "
                "read repeatedly on its own frames", "r0_m": r0, "outer_scale_m": outer}
    else:
        slopes, commands = record_loop(sim, record_gain, record_frames, scan_seed)
        seen_gain = dm_gain_from_slopes(slopes[200:], commands[200:], d)
        pol = pseudo_open_loop_slopes(slopes[200:], commands[200:], d, seen_gain)
        noise = slope_noise_from_pol(pol)
        priors = {outer: sim_prior_nm2(sim, 1.0, outer) for outer in OUTER_SCALES_M}
        found = fit_turbulence(pol, noise, d, v, priors)
        prior = priors[found["outer_scale_m"]] * found["r0_m"] ** (-5 / 3)
        info = {"kind": kind, "knowledge": f"telemetry: {record_frames} frames of the integrator (gain {record_gain}, "
                "10 nm dither) on the scan realisation", "dm_gain_seen": seen_gain, **found}
    info["slope_noise_rms"] = {"mean": float(np.sqrt(noise.mean())), "min": float(np.sqrt(noise.min())),
                               "max": float(np.sqrt(noise.max()))}
    scan, built = {}, {}
    for w in map(float, weights):
        sim.reconstructor = built[w] = map_reconstructor(d, v, prior, noise, w)
        scan[w] = scan_integrator(sim, gains, loop_frames, scan_seed, settle_frames)
        progress(f"[{kind}] w={w:g}: best-gain integrator {scan[w]['median_rms_nm']:.2f} nm "
                 f"(gain {scan[w]['gain']}) on the scan realisation")
    best = min(scan, key=lambda w: scan[w]["median_rms_nm"])
    sim.reconstructor = built[best]
    source = "the simulator's r0 and L0" if kind == "map" else "turbulence and noise estimated from the loop's recording"
    sim.reconstructor_name = f"the MAP reconstructor ({source}, weight {best:g})"
    noise_gain = float(np.linalg.norm(sim.reconstructor) / np.linalg.norm(least_squares))
    info.update(weight=best, weight_scan={f"{w:g}": s["median_rms_nm"] for w, s in scan.items()},
                scan_seed=scan_seed, frobenius_vs_least_squares=noise_gain)
    progress(f"[{kind}] chosen w={best:g}; |R| / |R_least_squares| = {noise_gain:.3f}")
    return info
