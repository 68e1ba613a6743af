"""Predictive Fourier control on another simulator's actuators: its lattice as eofnn's square grid.

eofnn's :class:`~eofnn.control.fourier.FourierPredictor` reads its actuators as the pixels of a square grid in
row-major order. Another simulator's actuators on a square lattice (OOPAO's Fried DM: ``N + 1`` across, those
within reach of the pupil) are such a grid once ordered: :class:`LatticeGrid` orders them and :class:`LatticeControl`
runs the controller in that order inside the loop (:func:`~eofnn.interop.loop.run_closed_loop`). Building the
controller from a loop's telemetry and eofnn's twin of the system is a study's work:
:func:`eofnn.studies.pfc.pfc_in_loop` (``pfc_in_loop`` is still reachable here, with a deprecation warning, for one
release).
"""

from __future__ import annotations

import warnings

import numpy as np

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


def __getattr__(name: str):
    """``pfc_in_loop`` moved to :mod:`eofnn.studies.pfc`: reached here with a DeprecationWarning, for one release."""
    if name == "pfc_in_loop":
        warnings.warn("eofnn.interop.pfc.pfc_in_loop moved to eofnn.studies.pfc.pfc_in_loop; the old path goes in the "
                      "next release", DeprecationWarning, stacklevel=2)
        from eofnn.studies.pfc import pfc_in_loop

        return pfc_in_loop
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
