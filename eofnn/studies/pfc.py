"""Predictive Fourier control in another simulator's loop, built from that loop's telemetry (the third classical
contender beside the integrator and the LQG in :mod:`eofnn.studies.antialias`).

eofnn's :class:`~eofnn.control.fourier.FourierPredictor` reads its actuators as the pixels of a square grid in
row-major order. Another simulator's actuators on a square lattice (OOPAO's Fried DM: ``N + 1`` across, those within
reach of the pupil) are such a grid once ordered (:class:`eofnn.interop.pfc.LatticeGrid`), and
:class:`~eofnn.interop.pfc.LatticeControl` runs the controller in that order inside the loop. The controller itself
is built exactly as in eofnn's loop (:func:`eofnn.control.frozen_flow.pfc_from_pol`): the POL values recorded in the
loop (formed with the identified gain), the white noise from the identification, the winds and their weights
identified from the same telemetry (:mod:`eofnn.control.wind`), per-mode variances, and the stationary Kalman gain
of each mode. What the loop's own calibration cannot tell it, the outer scale and that the sensor averages over
subapertures (the aliases' share of each mode), comes from eofnn's twin of the system
(:func:`eofnn.studies.transfer.eofnn_twin`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from eofnn.control.config import PfcConfig
from eofnn.control.frozen_flow import pfc_from_pol
from eofnn.errors import require
from eofnn.interop.pfc import LatticeControl, LatticeGrid


@dataclass(frozen=True)
class _LoopScenario:
    """What :func:`~eofnn.control.frozen_flow.pfc_from_pol` reads of a scenario, for another simulator's loop."""

    grid: LatticeGrid
    frame_rate_hz: float
    atmosphere: object
    plant: object


def pfc_in_loop(sim, pol, dm_gain: float, noise_nm: float | None, config: PfcConfig | None = None) -> LatticeControl:
    """Predictive Fourier control of ``sim``'s loop from its ``(R, T, K)`` POL values (formed with the identified
    ``dm_gain``; ``noise_nm``: the identified white noise per actuator, else estimated), as a loop controller.
    ``config.noise_covariance: reconstructor`` takes the noise's shape from the loop's own reconstructor,
    ``R R^T`` (``sim.reconstructor``, ``(K, n_slopes)``: its slope noise taken as white and equal on every slope),
    scaled to that variance per actuator."""
    from eofnn.studies.transfer import eofnn_twin

    config = config or PfcConfig()
    grid = LatticeGrid(sim.positions_m)
    twin = eofnn_twin(sim).eofnn_scenario(None, screen_frames=50)
    scenario = _LoopScenario(grid, float(sim.frame_rate_hz), twin.atmosphere, twin.plant)
    shape = None
    if config.noise_covariance == "reconstructor":
        require(getattr(sim, "reconstructor", None) is not None,
                f"pfc.noise_covariance='reconstructor' is invalid in {type(sim).__name__}'s loop: it exposes no "
                "reconstructor (K x slopes); use 'white'")
        r = torch.as_tensor(np.asarray(sim.reconstructor, dtype=np.float64))[grid.order]
        shape = r @ r.T
    controller = pfc_from_pol(pol[..., grid.order], scenario, config, dm_gain,
                              noise_variance=None if noise_nm is None else float(noise_nm) ** 2, noise_shape=shape)
    return LatticeControl(controller, sim.delay_frames, grid.order)
