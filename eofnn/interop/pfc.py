"""Predictive Fourier control in another simulator's loop, built from that loop's telemetry (issue 30's third
classical contender beside the integrator and the LQG).

eofnn's :class:`~eofnn.control.fourier.FourierPredictor` reads its actuators as the pixels of a square grid in
row-major order. Another simulator's actuators on a square lattice (OOPAO's Fried DM: ``N + 1`` across, those
within reach of the pupil) are such a grid once ordered: :class:`LatticeGrid` orders them and :class:`LatticeControl`
runs the controller in that order inside the loop. The controller itself is built exactly as in eofnn's loop
(:func:`eofnn.control.frozen_flow.pfc_from_pol`): the POL values recorded in the loop (formed with the identified
gain), the white noise from the identification, the winds and their weights identified from the same telemetry
(:mod:`eofnn.control.wind`), per-mode variances, and the stationary Kalman gain of each mode. What the loop's own
calibration cannot tell it, the outer scale and that the sensor averages over subapertures (the aliases' share of
each mode), comes from eofnn's twin of the system (:func:`eofnn.interop.transfer.eofnn_twin`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eofnn.control.config import PfcConfig
from eofnn.control.frozen_flow import pfc_from_pol
from eofnn.errors import ConfigError
from eofnn.interop.loop import TorchControl
from eofnn.sim.layout import ActuatorLayout


class LatticeGrid:
    """Actuators on a square lattice (an :class:`~eofnn.sim.layout.ActuatorLayout` whose ``lattice_indices`` exist)
    as :class:`~eofnn.control.fourier.FourierBasis` reads eofnn's grid: ``order`` takes the layout's actuators to
    row-major lattice order, in which ``indices`` ``(K, 2)`` (row, column), ``positions_m`` and ``ptt_basis`` are
    given, with ``neighbours``; ``n_across`` is the lattice's larger side."""

    def __init__(self, positions_m) -> None:
        layout = ActuatorLayout(positions_m)
        lattice = layout.lattice_indices
        if lattice is None:
            raise ConfigError("predictive Fourier control needs the actuators on a square lattice: these are not (a "
                              "triangulated layout has no Fourier grid)")
        lattice = lattice - lattice.min(0)
        self.order = np.lexsort((lattice[:, 1], lattice[:, 0]))
        self.indices = lattice[self.order]
        self.positions_m = layout.positions_m[self.order]
        self.pitch_m = float(layout.pitch_m)
        self.n_across = int(lattice.max()) + 1
        self.n_actuators = len(lattice)
        self._layout = ActuatorLayout(self.positions_m)

    def neighbours(self, radius: float):
        """The actuators within ``radius`` pitches of each, itself first (lattice order, as
        :meth:`ActuatorLayout.neighbours <eofnn.sim.layout.ActuatorLayout.neighbours>`: ``K`` beyond the edge)."""
        return self._layout.neighbours(radius)

    def ptt_basis(self) -> np.ndarray:
        """Orthonormal ``(K, 3)`` piston, tip and tilt over the actuators (lattice order)."""
        return self._layout.ptt_basis()


class LatticeControl(TorchControl):
    """A controller built on a :class:`LatticeGrid` in the simulator's loop: measurements go to it in lattice order,
    its commands come back in the simulator's."""

    def __init__(self, controller, delay_frames: int, order: np.ndarray) -> None:
        super().__init__(controller, delay_frames)
        self.order = np.asarray(order)

    def step(self, measurement: np.ndarray) -> np.ndarray:
        command = np.empty(len(self.order))
        command[self.order] = super().step(np.asarray(measurement, dtype=np.float64)[self.order])
        return command


@dataclass(frozen=True)
class _LoopScenario:
    """What :func:`~eofnn.control.frozen_flow.pfc_from_pol` reads of a scenario, for another simulator's loop."""

    grid: LatticeGrid
    frame_rate_hz: float
    atmosphere: object
    plant: object


def pfc_in_loop(sim, pol, dm_gain: float, noise_nm: float | None, config: PfcConfig | None = None) -> LatticeControl:
    """Predictive Fourier control of ``sim``'s loop from its ``(R, T, K)`` POL values (formed with the identified
    ``dm_gain``; ``noise_nm``: the identified white noise per actuator, else estimated), as a loop controller."""
    from eofnn.interop.transfer import eofnn_twin

    grid = LatticeGrid(sim.positions_m)
    twin = eofnn_twin(sim).eofnn_scenario(None, screen_frames=50)
    scenario = _LoopScenario(grid, float(sim.frame_rate_hz), twin.atmosphere, twin.plant)
    controller = pfc_from_pol(pol[..., grid.order], scenario, config or PfcConfig(), dm_gain,
                              noise_variance=None if noise_nm is None else float(noise_nm) ** 2)
    return LatticeControl(controller, sim.delay_frames, grid.order)
