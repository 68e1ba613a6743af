"""The statistics a twin is identified from (steps 3-5 of :mod:`eofnn.training.twin`): the pseudo-open-loop
signal, the WFS noise's covariance from its lagged structure, and r0 and L0 against the covariance of the twin's own
noise-free turbulence."""

from __future__ import annotations

import json
import math

import numpy as np

from eofnn.lazy import lazy_module

torch = lazy_module("torch")

#: The wavelength r0 is given at (m).
R0_WAVELENGTH_M = 5e-7
#: Outer scales (m) the structure function is fitted over.
OUTER_SCALES_M = (10.0, 20.0, 40.0)
#: The r0 (m, at :data:`R0_WAVELENGTH_M`) of the reference turbulence the record's is scaled from.
R0_REFERENCE_M = 0.1
#: Frames of each reference stream (at most; two realisations).
REFERENCE_FRAMES = 3000
#: Frames per segment of the periodograms :func:`noise_floor` fits (Hann window, half overlap).
NOISE_SEGMENT_FRAMES = 128
#: The band (cycles per frame) :func:`noise_floor` fits: the upper half of the temporal frequencies.
NOISE_BAND = (0.25, 0.5)
#: The power law of the turbulence's high-frequency tail :func:`noise_floor` fits beside the white floor.
TAIL_EXPONENT = -11 / 3
#: The band (cycles per frame, below :data:`NOISE_BAND`) where the record's turbulence spectrum is compared with the
#: twin's, to tell how much of the twin's high-frequency floor the record has (:func:`seeing_and_noise`).
TAIL_MATCH_BAND = (0.1875, 0.25)

def pseudo_open_loop(y: np.ndarray, wfs: np.ndarray, dm_gain: float, delay_frames: float) -> np.ndarray:
    """``s_hat(n) = wfs(n) - g DM-term(n)`` (module docstring, 3), ``(frames, K)`` nm."""
    fraction = float(delay_frames) - math.floor(float(delay_frames))
    acting = y if fraction == 0 else np.concatenate([y[:1], (1 - fraction) * y[1:] + fraction * y[:-1]])
    return wfs - dm_gain * acting


def noise_covariance(pol: np.ndarray) -> np.ndarray:
    """``C_v = (4 D(1) - D(2)) / 6`` (module docstring, 4), ``(K, K)`` nm², of ``(frames, K)`` POL values."""
    d1, d2 = pol[1:] - pol[:-1], pol[2:] - pol[:-2]
    return (4 * d1.T @ d1 / len(d1) - d2.T @ d2 / len(d2)) / 6


def _periodograms(pol: np.ndarray, segment: int):
    """``(f, [z])``: frequencies (cycles per frame) and each Hann-windowed, half-overlapping segment's FFT divided by
    the window's norm (so that white noise of covariance ``C`` gives ``E[z* z^T] = C`` at every frequency)."""
    frames = len(pol)
    seg = int(min(segment, max(16, frames // 4)))
    window = np.hanning(seg + 1)[:-1]
    norm = math.sqrt(float(window @ window))
    chunks = [pol[s:s + seg] for s in range(0, frames - seg + 1, seg // 2)]
    return np.fft.rfftfreq(seg), [np.fft.rfft((c - c.mean(0)) * window[:, None], axis=0) / norm for c in chunks]


def noise_floor(pol: np.ndarray, segment: int = NOISE_SEGMENT_FRAMES) -> np.ndarray:
    """``C_v`` (``(K, K)`` nm²) as the white floor of the ``(frames, K)`` POL values' temporal cross-periodogram over
    :data:`NOISE_BAND`: each element fitted (least squares, the same weights for all, so the fit is one linear map
    of the periodogram and does not depend on the basis) as ``C + A f^`` :data:`TAIL_EXPONENT`, the turbulence's
    high-frequency tail beside the white noise, whose level is ``C``. Hann-windowed segments of ``segment`` frames
    (fewer if the record is short), half overlapping, each less its mean."""
    return _floor(*_periodograms(pol, segment))


def _floor(f: np.ndarray, spectra: list) -> np.ndarray:
    """:func:`noise_floor` of :func:`_periodograms`' ``(f, spectra)``."""
    band = (f >= NOISE_BAND[0]) & (f <= NOISE_BAND[1])
    design = np.column_stack([np.ones(band.sum()), (f[band] / NOISE_BAND[0]) ** TAIL_EXPONENT])
    weights = np.linalg.pinv(design)[0]  # the floor's coefficient of each frequency
    return sum(((z[band].conj() * weights[:, None]).T @ z[band]).real for z in spectra) / len(spectra)


def mean_spectrum(pol: np.ndarray, segment: int = NOISE_SEGMENT_FRAMES) -> np.ndarray:
    """The periodogram (:func:`noise_floor`'s) of ``(frames, K)`` values averaged over the K of them, ``(segment // 2
    + 1,)`` nm² per unit of white noise's level."""
    return _mean(_periodograms(pol, segment)[1])


def _mean(spectra: list) -> np.ndarray:
    """:func:`mean_spectrum` of :func:`_periodograms`' spectra."""
    return sum((abs(z) ** 2).mean(1) for z in spectra) / len(spectra)


def floor_and_spectrum(pol: np.ndarray, segment: int = NOISE_SEGMENT_FRAMES) -> tuple[np.ndarray, np.ndarray]:
    """:func:`noise_floor` and :func:`mean_spectrum` of ``pol`` together, from one set of periodograms."""
    f, spectra = _periodograms(pol, segment)
    return _floor(f, spectra), _mean(spectra)


def ptt_projector(positions: np.ndarray) -> np.ndarray:
    """``(K, K)``: the projector that removes piston, tip and tilt from values at ``positions`` (m, ``(K, 2)``)."""
    basis = np.column_stack([np.ones(len(positions)), positions - positions.mean(0)])
    q, _ = np.linalg.qr(basis)
    return np.eye(len(positions)) - q @ q.T


def record_range(reconstructor: np.ndarray | None, positions_m: np.ndarray, grid_positions_m: np.ndarray,
                 tolerance: float = 1e-8) -> np.ndarray | None:
    """``(K', K')``: the projector, on the twin's actuators at ``grid_positions_m``, on the range of the record's
    ``(K, S)`` reconstructor (the actuator-space values ``wfs = R @ slopes`` can take: the modes it reconstructs;
    singular values below ``tolerance`` of the largest are its null space), the record's actuators at ``positions_m``
    matched to the twin's; ``None`` without a reconstructor, where it reconstructs every mode, or where the twin's
    actuators are not the record's."""
    if reconstructor is None or len(grid_positions_m) != len(positions_m):
        return None
    u, singular, _ = np.linalg.svd(np.asarray(reconstructor, dtype=np.float64), full_matrices=False)
    rank = int((singular > tolerance * singular[0]).sum())
    gap = np.linalg.norm(np.asarray(grid_positions_m)[:, None] - np.asarray(positions_m)[None], axis=-1)
    match = gap.argmin(1)
    if rank >= len(positions_m) or len(set(match.tolist())) != len(match) or gap.min(1).max() > 1e-6:
        return None
    basis = u[match, :rank]
    return basis @ basis.T


def reference_covariances(config: dict, layers: list[dict], frames: int, *, realisations: int = 2,
                          seed: int = 0, record: tuple | None = None) -> dict[float, tuple]:
    """``{L0: (cov, leak, positions, spectrum)}``: the ``(K', K')`` covariance (nm²) and :func:`noise_floor` of the
    noise-free turbulence, the ``(K', 2)`` positions (m) of the twin's actuators and the turbulence's
    :func:`mean_spectrum`, as the twin's sensor sees it, at ``r0 =`` :data:`R0_REFERENCE_M` (at
    :data:`R0_WAVELENGTH_M`) and each outer scale of :data:`OUTER_SCALES_M`, the identified winds, over
    ``realisations`` streams of ``frames`` frames (``config``: the twin's scenario fields).

    ``record``: ``(reconstructor, positions_m)`` of the record, ``(K, S)`` and ``(K, 2)`` (``reconstructor`` may be
    ``None``). Where the record's reconstructor outputs fewer modes than the twin's does (another singular-value cut:
    OOPAO's loop drops below 0.15 of the largest, eofnn's below 0.1 at 20 across), the streams are projected on its
    range (:func:`record_range`) before their statistics: the modes it drops are the worst-seen, most amplified
    ones, and left in the reference they add to its structure function what the record's cannot have (r0 then came
    out ~10% high on OOPAO's records). Streams already in that range are left as they are (bit for bit)."""
    from eofnn.sim.scenario import Scenario

    out, projector = {}, None
    for i, l0 in enumerate(OUTER_SCALES_M):
        cfg = json.loads(json.dumps(config))
        cfg["atmosphere"].update(r0_m=R0_REFERENCE_M, r0_wavelength_m=R0_WAVELENGTH_M, outer_scale_m=l0,
                                 screen_frames=frames,
                                 layers=[{"cn2_fraction": lay["weight"], "wind_speed_mps": lay["speed_mps"],
                                          "wind_direction_deg": lay["direction_deg"]} for lay in layers])
        cfg["plant"]["wfs_noise_nm"] = 0.0
        if "sensor" in cfg:
            cfg["sensor"]["detector"] = None
        scenario = Scenario.from_dict(cfg)
        s = scenario.turbulence(seed, "twin_reference", realisations).frames(0, frames).numpy()
        if i == 0 and record is not None:  # every outer scale's twin has the same actuators
            projector = record_range(record[0], record[1], np.asarray(scenario.grid.positions_m))
        if projector is not None and np.linalg.norm(s - s @ projector) > 1e-10 * np.linalg.norm(s):
            s = s @ projector
        floors, spectra = zip(*(floor_and_spectrum(r) for r in s), strict=True)
        out[l0] = (sum(np.cov(r.T) for r in s) / len(s), sum(floors) / len(s), np.asarray(scenario.grid.positions_m),
                   sum(spectra) / len(s))
    return out


def _structure(cov: np.ndarray, distance: np.ndarray, bins: np.ndarray) -> np.ndarray:
    d = np.diag(cov)
    pairs = d[:, None] + d[None, :] - 2 * cov
    which = np.digitize(distance, bins)
    return np.array([pairs[which == b].mean() if (which == b).any() else np.nan for b in range(1, len(bins))])


def _floor_share(spectrum: np.ndarray, reference: np.ndarray, raw: float, leak: float, steps: int = 60) -> float:
    """The share ``a`` (0 to 1) of the twin's floor ``leak`` (nm², per actuator) that a record whose white floor is
    ``raw`` (nm²) has: ``a`` solves ``a = median((spectrum - noise) / reference)`` with ``noise = raw - a leak``
    and ``0 <= noise`` (bisection on the noise: the difference is monotone where the twin's spectrum is at least its
    floor; the share is well determined where the twin's spectrum over the band is well above its floor)."""
    def excess(noise: float) -> float:
        share = float(np.clip(np.median((spectrum - noise) / reference), 0.0, 1.0))
        return noise - raw + share * leak

    low, high = max(raw - max(leak, 0.0), 0.0), max(raw, 0.0)
    for _ in range(steps):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if excess(middle) < 0 else (low, middle)
    return float(np.clip((raw - 0.5 * (low + high)) / leak, 0.0, 1.0)) if leak > 0 else 0.0


def seeing_and_noise(pol: np.ndarray, references: dict, positions_m: np.ndarray, pitch_m: float,
                     iterations: int = 4) -> tuple[np.ndarray, dict]:
    """``(C_v, seeing)``: the noise covariance and :func:`fit_seeing` of ``(frames, K)`` POL values, together.
    :func:`noise_floor` takes the turbulence's tail as ``f^(-11/3)``; a sensor whose turbulence keeps a floor of its
    own at high frequency (an aliased Shack-Hartmann's, which is not smooth) leaves that floor in it. The references
    tell how large the twin's is per unit of their turbulence (their own :func:`noise_floor`, scaling as
    ``r0^(-5/3)``), and the record tells how much of it it has: its turbulence's spectrum over
    :data:`TAIL_MATCH_BAND` (its :func:`mean_spectrum` less the noise found) against the twin's at the r0 found, the
    median of the ratios over the band's frequencies, within 0 and 1 (``seeing["aliasing_share"]``). That share of
    the twin's floor is removed, and r0 fitted again with the noise so corrected."""
    (raw, spectrum), total = floor_and_spectrum(pol), np.cov(pol.T)
    f = np.fft.rfftfreq(2 * (len(spectrum) - 1))
    match = (f >= TAIL_MATCH_BAND[0]) & (f < TAIL_MATCH_BAND[1])
    cv, seeing, share = raw, fit_seeing(total - raw, references, positions_m, pitch_m), 1.0
    for _ in range(iterations):
        _, leak, where, reference_spectrum = references[seeing["outer_scale_m"]]
        scale = (R0_REFERENCE_M / seeing["r0_m"]) ** (5 / 3)
        if leak.shape != raw.shape or not np.allclose(where, positions_m):  # another layout: its mean, per actuator
            leak = np.eye(len(raw)) * float(np.diag(leak).mean())
        if len(reference_spectrum) == len(spectrum):  # else (a record too short for the segments) all of it
            share = _floor_share(spectrum[match], scale * reference_spectrum[match], float(np.diag(raw).mean()),
                                 scale * float(np.diag(leak).mean()))
        cv = raw - share * scale * leak
        seeing = fit_seeing(total - cv, references, positions_m, pitch_m)
    seeing["aliasing_share"] = share
    return cv, seeing


def fit_seeing(turbulence_cov: np.ndarray, references: dict[float, np.ndarray], positions_m: np.ndarray,
               pitch_m: float) -> dict:
    """r0 (m, at :data:`R0_WAVELENGTH_M`) and L0 (m) of a ``(K, K)`` turbulence covariance against the
    :func:`reference_covariances` (module docstring, 5): ``{"r0_m", "outer_scale_m", "misfit": {L0: rms log
    misfit}}``. The structure function ``D(r)`` of each, piston, tip and tilt projected out, averaged over pairs
    of actuators in bins of a pitch from 1.5 pitches to half the pupil; ``D`` scales as ``r0^(-5/3)``."""
    def structure(cov: np.ndarray, positions: np.ndarray) -> np.ndarray:
        p = ptt_projector(positions)
        return _structure(p @ cov @ p, np.linalg.norm(positions[:, None] - positions[None], axis=-1), bins)

    extent = float(np.ptp(positions_m, axis=0).max())
    bins = np.arange(1.5 * pitch_m, max(0.5 * extent, 3 * pitch_m) + pitch_m / 2, pitch_m)
    measured = structure(turbulence_cov, positions_m)
    results = {}
    for l0, (reference, _, where, *_) in references.items():
        model = structure(reference, where)
        good = np.isfinite(measured) & (measured > 0) & np.isfinite(model) & (model > 0)
        ratio = np.log(measured[good] / model[good])
        results[l0] = (float(ratio.mean()), float(ratio.std()))
    best = min(results, key=lambda k: results[k][1])
    return {"r0_m": float(R0_REFERENCE_M * math.exp(-0.6 * results[best][0])), "outer_scale_m": best,
            "misfit": {str(k): round(v[1], 4) for k, v in results.items()}}
