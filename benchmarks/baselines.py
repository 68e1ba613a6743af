"""Straightforward numpy / HCIPy implementations that eofnn is compared against.

These are what one would write without eofnn: a Python loop over HCIPy's ``InfiniteAtmosphericLayer``, a numpy
closed loop, a per-actuator ``numpy.linalg.lstsq``. They do the same work as the eofnn code they are timed
against (same grid, same piston/tip/tilt removal, same filter, same loop equations), not a cleverer algorithm.
"""

from __future__ import annotations

import math

import hcipy
import numpy as np

from eofnn.sim.atmosphere.turbulence import Atmosphere
from eofnn.sim.grid import ActuatorGrid

#: HCIPy phase (rad) at wavelength lambda times lambda / (2 pi) is the OPD in metres.
_NM_PER_M = 1e9


class HcipyTurbulence:
    """Turbulence on the actuator grid the plain HCIPy way: one ``InfiniteAtmosphericLayer`` per layer.

    The HCIPy grid has ``n_across`` pixels across the pupil at the actuator pitch (its pixel centres are the
    actuator centres); each frame every layer is evolved to the frame's time, the phase is read at the active
    actuators, converted to OPD in nm, summed over layers, and piston/tip/tilt is projected out.
    """

    def __init__(self, atmosphere: Atmosphere, grid: ActuatorGrid, frame_rate_hz: float, seed: int = 0,
                 wavelength_m: float = 500e-9) -> None:
        self.grid, self.frame_period_s, self.wavelength_m = grid, 1.0 / frame_rate_hz, wavelength_m
        pupil_grid = hcipy.make_pupil_grid(grid.n_across, grid.diameter_m)
        rng = np.random.default_rng(seed)
        self.layers = []
        for layer in atmosphere.layers:
            cn2 = hcipy.Cn_squared_from_fried_parameter(atmosphere.layer_r0_m(layer), atmosphere.r0_wavelength_m)
            angle = math.radians(layer.wind_direction_deg)
            velocity = layer.wind_speed_mps * np.array([math.cos(angle), math.sin(angle)])
            self.layers.append(hcipy.InfiniteAtmosphericLayer(
                pupil_grid, cn2, atmosphere.outer_scale_m, velocity=velocity, seed=rng.integers(2**32)))
        self.active = grid.mask.ravel()
        self.ptt = grid.ptt_basis()
        self.remove_ptt = atmosphere.remove_ptt
        self.next_frame = 0

    def frame(self) -> np.ndarray:
        """OPD in nm of the next frame at the active actuators, ``(n_actuators,)``."""
        t = self.next_frame * self.frame_period_s
        self.next_frame += 1
        opd = np.zeros(int(self.active.sum()))
        for layer in self.layers:
            layer.evolve_until(t)
            phase = np.asarray(layer.phase_for(self.wavelength_m))[self.active]
            opd += phase * (self.wavelength_m / (2 * np.pi) * _NM_PER_M)
        if self.remove_ptt:
            opd -= self.ptt @ (self.ptt.T @ opd)
        return opd

    def frames(self, n: int) -> np.ndarray:
        """The next ``n`` frames, ``(n, n_actuators)``."""
        out = np.empty((n, int(self.active.sum())))
        for i in range(n):
            out[i] = self.frame()
        return out


class NumpyPredictiveLoop:
    """The closed loop of :func:`eofnn.sim.run_loop` with a linear predictive controller, in plain numpy.

    Same equations as ``run_loop`` + ``PredictiveController`` + ``LinearFilter`` (per actuator) with a nominal plant:
    ``y(n) = sum(h * W)`` over the history ``h``, ``eps(n) = s(n) + y(n)``, ``wfs(n) = eps(n)``, a ``delay``-frame ring
    of measurements, zero commands until the history is full, and the per-frame residual RMS.

    Parameters
    ----------
    weights : ndarray
        ``(n_actuators, taps)`` filter weights.
    kind : {"open_loop", "closed_loop"}
        Pseudo-open-loop history ``[s_hat(n-d) ...]`` or closed-loop ``[y(n-1..n-p), eps(n-d..n-d-p+1)]``.
    history_length, delay : int
        ``p`` and ``d``.
    """

    def __init__(self, weights: np.ndarray, kind: str, history_length: int, delay: int) -> None:
        self.w, self.kind, self.p, self.d = np.asarray(weights, float), kind, history_length, delay
        oldest = delay + history_length - 1
        self.first_frame = max(oldest, history_length) if kind == "closed_loop" else oldest

    def run(self, s: np.ndarray) -> np.ndarray:
        """Close the loop on turbulence ``s`` ``(frames, n_actuators)``; returns the residual RMS per frame."""
        n_frames, k = s.shape
        p, d, w = self.p, self.d, self.w
        taps = w.shape[1]
        h = np.zeros((k, taps))
        y_past = np.zeros((k, max(p, d)))
        wfs_ring = np.zeros((d, k))
        eps = np.empty((n_frames, k))
        for n in range(n_frames):
            wfs = wfs_ring[n % d]
            if self.kind == "open_loop":
                s_hat = wfs - y_past[:, d - 1]
                h[:, 1:] = h[:, :-1]
                h[:, 0] = s_hat
            else:
                h[:, p + 1:] = h[:, p:-1]
                h[:, p] = wfs
                h[:, :p] = y_past[:, :p]
            y = (h * w).sum(axis=1) if n >= self.first_frame else np.zeros(k)
            y_past[:, 1:] = y_past[:, :-1]
            y_past[:, 0] = y
            eps[n] = s[n] + y
            wfs_ring[n % d] = eps[n]
        return np.sqrt((eps**2).mean(axis=1))

    def step_only(self, wfs: np.ndarray) -> np.ndarray:
        """One controller step on a measurement (the part that has to fit in a frame), history kept in ``self``."""
        if not hasattr(self, "_h"):
            self._h = np.zeros_like(self.w)
            self._y = np.zeros((self.w.shape[0], max(self.p, self.d)))
        h, p, d = self._h, self.p, self.d
        if self.kind == "open_loop":
            h[:, 1:] = h[:, :-1]
            h[:, 0] = wfs - self._y[:, d - 1]
        else:
            h[:, p + 1:] = h[:, p:-1]
            h[:, p] = wfs
            h[:, :p] = self._y[:, :p]
        y = (h * self.w).sum(axis=1)
        self._y[:, 1:] = self._y[:, :-1]
        self._y[:, 0] = y
        return y


def open_loop_regression(s: np.ndarray, history_length: int, delay: int) -> tuple[np.ndarray, np.ndarray]:
    """Regressors ``(samples, K, p)`` = ``[s(n-d), ..., s(n-d-p+1)]`` and targets ``-s(n)`` ``(samples, K)``."""
    first = delay + history_length - 1
    t = s.shape[0]
    x = np.stack([s[first - lag: t - lag] for lag in range(delay, delay + history_length)], axis=-1)
    return x, -s[first:]


def numpy_lstsq_per_actuator(x: np.ndarray, target: np.ndarray) -> np.ndarray:
    """One ``numpy.linalg.lstsq`` per actuator: ``(K, p)`` weights from ``(samples, K, p)`` and ``(samples, K)``."""
    k = x.shape[1]
    return np.stack([np.linalg.lstsq(x[:, i], target[:, i], rcond=None)[0] for i in range(k)])
