"""A pyramid's optical gains: its response to a small probe about a residual, against its response about a flat
wavefront, per mode.

The pyramid (:mod:`eofnn.sim.sensing.pyramid`) is linear only about a flat wavefront; about a residual its response
to a small probe of mode ``m`` is smaller (the residual smears the PSF over the faces as modulation does). Per mode,
the gain is the projection of the response about the residual on the response about a flat wavefront,
``<D_res m, D_0 m> / <D_0 m, D_0 m>`` (the convolutional model's and the gain-sensing camera's quantity:
Chambouleyron et al. 2020, A&A 644, A6; Fauvarque et al. 2019, JATIS 5, 1).

A loop measures them on its own residual with :class:`OpticalGainProbe` (``run_loop``'s ``on_chunk``): it keeps the
residual over the pupil at a few settled frames and gives, about each, the optical gains of the first Karhunen-Loeve
command modes: the mean over those residuals per mode, and the means over the low and the high orders (what a
pyramid scenario's ``metrics.json`` and ``eofnn simulate``'s summary report).
"""

from __future__ import annotations

import numpy as np
import torch

from eofnn.errors import require
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.sensing.pyramid_optics import as_phase
from eofnn.validation import Interval, check_value


def kl_modes(grid: ActuatorGrid, n_modes: int) -> np.ndarray:
    """``(K, n_modes)`` orthonormal command-space Karhunen-Loève modes of Kolmogorov turbulence on ``grid``'s
    actuators, piston removed, in decreasing variance: the eigenvectors of ``-P S P / 2`` (``S`` the structure
    function ``|x_i - x_j|^(5/3)`` between actuators, ``P`` the piston-removing projector)."""
    check_value("n_modes", n_modes, Interval(1, grid.n_actuators - 1, integer=True, unit="modes"))
    return _kl_basis(grid, n_modes)


def _kl_basis(grid: ActuatorGrid, n_modes: int) -> np.ndarray:
    """:func:`kl_modes` for ``n_modes`` already checked."""
    x = grid.positions_m
    structure = np.hypot(*(x[:, None, :] - x[None, :, :]).transpose(2, 0, 1)) ** (5 / 3)
    k = len(x)
    p = np.eye(k) - 1.0 / k
    values, vectors = np.linalg.eigh(-0.5 * p @ structure @ p)
    return vectors[:, np.argsort(values)[::-1][:n_modes]]


def optical_gains(sensor, modes_nm: torch.Tensor, residual_nm: torch.Tensor,
                  amplitude_nm: float | None = None) -> torch.Tensor:
    """Optical gains ``(R, M)`` of ``(M, n_pupil)`` mode shapes (nm per unit) about each of ``(R, n_pupil)``
    residual phases (nm): ``<D_res m, D_0 m> / <D_0 m, D_0 m>`` per mode (module docstring), the responses by
    push-pull of ``amplitude_nm`` (the config's ``push_pull_nm`` if ``None``)."""
    modes = as_phase(modes_nm, sensor.n_pupil).reshape(-1, sensor.n_pupil)
    residuals = as_phase(residual_nm, sensor.n_pupil).reshape(-1, sensor.n_pupil)
    flat = sensor.response(modes, None, amplitude_nm)
    norm = (flat * flat).sum(-1)
    require(bool((norm > 0).all()), "a mode the pyramid does not see (zero response about a flat wavefront) has no "
                                    "optical gain: remove it from modes_nm")
    gains = [(sensor.response(modes, r, amplitude_nm) * flat).sum(-1) / norm for r in residuals]
    return torch.stack(gains)


def modal_optical_gains(sensor, residual_nm: torch.Tensor, n_modes: int,
                        amplitude_nm: float | None = None) -> tuple[torch.Tensor, np.ndarray]:
    """Optical gains of the first ``n_modes`` Karhunen-Loève command modes (:func:`kl_modes`) measured on a loop's
    residual: ``(gains, modes)``, ``gains`` ``(n_modes,)`` the mean of :func:`optical_gains` over the ``(R,
    n_pupil)`` residual phases (nm; e.g. frames of a closed loop's residual over the pupil), ``modes`` the ``(K,
    n_modes)`` orthonormal command modes they belong to (a controller compensates mode ``m`` by dividing its
    reconstruction ``modes[:, m] . y`` by ``gains[m]``)."""
    modes = kl_modes(sensor.grid, n_modes)
    shapes = sensor.dm_surface(torch.as_tensor(modes.T))
    return optical_gains(sensor, shapes, residual_nm, amplitude_nm).mean(0), modes


#: Modes measured (at most the actuators less piston) and settled frames whose residual is probed.
N_MODES, N_FRAMES = 50, 6


class OpticalGainProbe:
    """Collects a pyramid scenario's residual over the pupil at ``n_frames`` frames spread over the settled part of
    a run (``on_chunk``), then :meth:`result` measures the optical gains about them.

    Parameters
    ----------
    sensor : PyramidSensor
        The loop's pyramid, calibrated (a pyramid scenario's turbulence's ``operators.sensor``).
    settle_frames, frames : int
        The run's settling frames and its length.
    n_modes, n_frames : int
        Karhunen-Loève modes measured; frames probed (each gives one residual per realisation).
    compensation : OpticalGainCompensation or None
        The loop's compensation of its optical gains (:mod:`eofnn.sim.loop.optical_gain_compensation`), if any: the
        result then also gives the effective gains, the measured ones divided by those it divides by.
    """

    def __init__(self, sensor, settle_frames: int, frames: int, n_modes: int = N_MODES,
                 n_frames: int = N_FRAMES, compensation=None) -> None:
        self.sensor, self.compensation = sensor, compensation
        self.n_modes = min(n_modes, sensor.grid.n_actuators - 1)
        span = max(frames - settle_frames, 1)
        self.frames = sorted({settle_frames + (span * (2 * k + 1)) // (2 * n_frames) for k in range(n_frames)})
        self.residuals: list[torch.Tensor] = []

    @classmethod
    def of(cls, turbulence, settle_frames: int, frames: int, plant) -> OpticalGainProbe:
        """The probe of a pyramid scenario's ``turbulence`` run in ``plant`` (its compensation, if any, included)."""
        return cls(turbulence.operators.sensor, settle_frames, frames, compensation=turbulence.compensation(plant))

    def __call__(self, first: int, arrays: dict) -> None:
        stop = first + arrays["s"].shape[1]
        for frame in self.frames:
            if first <= frame < stop:
                self.residuals.append(arrays["pupil_residual"](frame))

    def result(self) -> dict | None:
        """``{"n_modes", "residuals", "residual_rms_nm", "gains", "low_orders", "low_order_mean", "high_orders",
        "high_order_mean"}`` (orders 1-based, inclusive), or ``None`` when no frame was probed (a diverged run);
        with a compensation also ``"compensation"`` (its summary) and ``"effective_gains"``,
        ``"effective_low_order_mean"``, ``"effective_high_order_mean"`` (the gains over those divided by: 1 where it
        compensates exactly)."""
        if not self.residuals:
            return None
        residuals = torch.cat(self.residuals)
        shapes = self.sensor.dm_surface(torch.as_tensor(_kl_basis(self.sensor.grid, self.n_modes).T))
        gains = optical_gains(self.sensor, shapes, residuals).mean(0)
        gains = [float(g) for g in gains]
        n = len(gains)
        low, high = max(1, n // 5), n // 2
        centred = residuals - residuals.mean(-1, keepdim=True)
        out = {"n_modes": n, "residuals": len(residuals),
               "residual_rms_nm": float(centred.pow(2).mean(-1).sqrt().mean()),
               "gains": gains,
               "low_orders": [1, low], "low_order_mean": sum(gains[:low]) / low,
               "high_orders": [high + 1, n], "high_order_mean": sum(gains[high:]) / (n - high)}
        if self.compensation is not None:
            divided = self.compensation.divided_by()
            effective = [g / float(divided[m]) if m < len(divided) else g for m, g in enumerate(gains)]
            out.update(compensation=self.compensation.summary(), effective_gains=effective,
                       effective_low_order_mean=sum(effective[:low]) / low,
                       effective_high_order_mean=sum(effective[high:]) / (n - high))
        return out
