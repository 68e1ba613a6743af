"""Telemetry on actuator layouts eofnn's simulator does not use: Fried, hexagonal, jittered.

The turbulence is frozen flow of a sum of random Fourier modes (a von Karman-like amplitude spectrum, spatial
frequencies up to the actuators' Nyquist), evaluated exactly at any position; the loop is the usual data controller
(integrator plus white dither) with a known DM: ``eps = s + g M y`` (``M`` a layout's shift model or the identity),
``wfs = eps + noise``. What this tests: identification and fitting on these layouts against a known plant and
predictable turbulence; not a physical sensor (no aliasing), and the misregistered DM is the same interpolation model
that identification assumes.
"""

from __future__ import annotations

import numpy as np
import torch

from eofnn.sim.layout import ActuatorLayout, apply_shift
from eofnn.telemetry.record import Telemetry

PITCH_M = 0.2


def fried_positions(n_subapertures: int = 10, pitch_m: float = PITCH_M) -> np.ndarray:
    """Fried geometry: actuators at the corners of the valid subapertures (centre inside the pupil of diameter
    ``n * pitch``, minus a 0.3 central obstruction when ``n >= 8``), ``n + 1`` across, row-major."""
    centres = (np.arange(n_subapertures) + 0.5 - n_subapertures / 2) * pitch_m
    yy, xx = np.meshgrid(centres, centres, indexing="ij")
    r = np.hypot(xx, yy) / (n_subapertures * pitch_m / 2)
    valid = (r <= 1) & (r >= (0.3 if n_subapertures >= 8 else 0.0))
    used = np.zeros((n_subapertures + 1, n_subapertures + 1), dtype=bool)
    for dr in (0, 1):
        for dc in (0, 1):
            used[dr:dr + n_subapertures, dc:dc + n_subapertures] |= valid
    corners = (np.arange(n_subapertures + 1) - n_subapertures / 2) * pitch_m
    cy, cx = np.meshgrid(corners, corners, indexing="ij")
    return np.stack([cx[used], cy[used]], 1)


def hex_positions(radius_m: float = 1.0, pitch_m: float = PITCH_M) -> np.ndarray:
    """A hexagonal lattice of pitch ``pitch_m`` inside a circle."""
    n = int(radius_m / pitch_m) + 2
    i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
    x = (i + 0.5 * j).ravel() * pitch_m
    y = (j * np.sqrt(3) / 2).ravel() * pitch_m
    keep = np.hypot(x, y) <= radius_m
    return np.stack([x[keep], y[keep]], 1)


def jittered_positions(n_across: int = 10, jitter: float = 0.15, seed: int = 0, pitch_m: float = PITCH_M) -> np.ndarray:
    """A square grid with every actuator moved by up to ``jitter`` pitches: an irregular layout."""
    rng = np.random.default_rng(seed)
    pos = fried_positions(n_across - 1, pitch_m)
    return pos + rng.uniform(-jitter, jitter, pos.shape) * pitch_m


def frozen_flow(positions_m: np.ndarray, frames: int, seed: int, *, rms_nm: float = 150.0, wind_mps=(8.0, 3.0),
                frame_rate_hz: float = 1000.0, n_modes: int = 300, pitch_m: float = PITCH_M) -> np.ndarray:
    """``(frames, K)`` turbulence (nm): ``sum_i a_i cos(2 pi f_i . (x - v t) + phi_i)``, ``|f|`` log-uniform from
    1/(20 m) to 1/(2 pitch), amplitudes ``~ |f|**(-11/6) * |f|`` (per log-frequency bin), scaled to ``rms_nm``."""
    rng = np.random.default_rng(seed)
    f = np.exp(rng.uniform(np.log(1 / 20.0), np.log(0.5 / pitch_m), n_modes))
    angle = rng.uniform(0, 2 * np.pi, n_modes)
    k = 2 * np.pi * f[:, None] * np.stack([np.cos(angle), np.sin(angle)], 1)  # (modes, 2) rad/m
    amplitude = f ** (-5 / 6)
    phase = rng.uniform(0, 2 * np.pi, n_modes)
    t = np.arange(frames) / frame_rate_hz
    temporal = np.exp(1j * (phase[None] - np.outer(t, k @ np.asarray(wind_mps))))  # (frames, modes)
    spatial = np.exp(1j * positions_m @ k.T)  # (K, modes)
    s = ((temporal * amplitude) @ spatial.T).real
    return s * rms_nm / s.std()


def record(positions_m: np.ndarray, frames: int = 4000, *, seed: int = 0, dm_gain: float = 2.0,
           misregistration=(0.0, 0.0), gain: float = 0.3, dither_nm: float = 10.0, noise_nm: float = 0.0,
           delay: int = 2, with_positions: bool = True) -> Telemetry:
    """Dithered integrator loop (``y(n) = c(n) + w(n)``, ``c(n) = c(n-1) - gain * wfs(n - delay)``) on the layout."""
    rng = np.random.default_rng(seed + 1000)
    s = torch.as_tensor(frozen_flow(positions_m, frames, seed))
    operator = ActuatorLayout(positions_m).shift_operator(*misregistration) if any(misregistration) else None
    k = s.shape[1]
    dither = torch.as_tensor(rng.standard_normal((frames, k)) * dither_nm)
    noise = torch.as_tensor(rng.standard_normal((frames, k)) * noise_nm)
    y, wfs = torch.zeros(frames, k, dtype=torch.float64), torch.zeros(frames, k, dtype=torch.float64)
    c = torch.zeros(k, dtype=torch.float64)
    for n in range(frames):
        if n >= delay:
            c = c - gain * wfs[n - delay]
        y[n] = c + dither[n]
        applied = y[n] if operator is None else apply_shift(y[n], operator)
        wfs[n] = s[n] + dm_gain * applied + noise[n]
    return Telemetry(y=y, wfs=wfs, delay_frames=delay, frame_rate_hz=1000.0,
                     positions_m=torch.as_tensor(positions_m) if with_positions else None)
