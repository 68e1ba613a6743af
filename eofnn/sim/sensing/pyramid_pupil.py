"""A pyramid's operators as the loop uses them: commands in nm of surface, the sensor's reading of the residual
phase, the pupil's fit of the phase, and the residual over the pupil from a few numbers per frame.

The same conventions as the Shack-Hartmann's (:mod:`eofnn.sim.sensing.pupil`): commands are in nm of DM surface
for a smooth shape (the peak-1 Gaussian influence functions divided by their lattice sum), ``R`` multiplied by it
and ``D`` divided by it, so ``P = R D`` does not change. Unlike the Shack-Hartmann's slopes, the pyramid's signal is
not linear in the phase: the loop cannot add the DM's term to a reading of the turbulence alone, it reads the
residual itself, ``wfs = R s(phi + IF u)`` (:meth:`PyramidLoopOperators.wfs`), one propagation per frame. The
residual over the pupil is scored as the Shack-Hartmann's is, from ``z = IF^T phi``, ``sum phi`` and ``sum phi²``
(:meth:`PyramidLoopOperators.products`, :meth:`PyramidLoopOperators.pupil_rms`); every sample point of the
pyramid is in the pupil.
"""

from __future__ import annotations

import numpy as np
import torch

from eofnn.errors import require
from eofnn.sim.sensing.least_squares import surface_per_command
from eofnn.sim.sensing.pupil import piston_removed_rms
from eofnn.sim.sensing.pyramid import PyramidSensor


class PyramidLoopOperators:
    """A built :class:`~eofnn.sim.sensing.pyramid.PyramidSensor` with the loop's operators (module docstring).

    Attributes
    ----------
    surface_per_command : float
        The lattice sum the influence functions are divided by.
    reconstructor, interaction_matrix, projector, fit_matrix : Tensor
        ``R`` ``(K, n_signals)`` (nm of command per unit of signal), ``D`` ``(n_signals, K)`` (signal per nm of
        command), ``P = R D`` ``(K, K)``, ``P (G + ridge)^-1`` ``(K, K)``.
    gram : scipy.sparse.csr_matrix
        ``G = IF^T IF`` ``(K, K)`` over the pupil's points.
    """

    def __init__(self, sensor: PyramidSensor) -> None:
        self.sensor = sensor
        self.n_pupil = sensor.n_pupil
        self.surface_per_command = surface_per_command(sensor.config.mechanical_coupling)
        influence = (sensor.influence / self.surface_per_command).tocsr()
        self.influence_t = influence.T.tocsr()  # IF^T (K, N_p)
        self.gram = (self.influence_t @ influence).tocsr()
        gram = self.gram.toarray()
        self.pupil_sums = torch.as_tensor(np.asarray(self.influence_t.sum(axis=1)).ravel())  # b = IF^T 1
        self.reconstructor = torch.as_tensor(sensor.reconstructor * self.surface_per_command)
        self.interaction_matrix = torch.as_tensor(sensor.interaction_matrix / self.surface_per_command)
        self.projector = torch.as_tensor(sensor.reconstructor @ sensor.interaction_matrix)
        # A tiny ridge keeps the Gram matrix of actuators whose influence barely reaches the pupil invertible.
        ridge = 1e-10 * np.diag(gram).max() * np.eye(len(gram))
        self.fit_matrix = self.projector @ torch.as_tensor(np.linalg.inv(gram + ridge))

    def surface(self, u: torch.Tensor) -> torch.Tensor:
        """``IF u``: the DM surface (nm) on the pupil's points for ``(rows, K)`` commands (nm)."""
        u = torch.as_tensor(u, dtype=torch.float64)
        return torch.as_tensor(np.asarray(u.reshape(-1, u.shape[-1]).cpu().numpy() @ self.influence_t)).reshape(
            *u.shape[:-1], self.n_pupil)

    def wfs(self, phase: torch.Tensor, u: torch.Tensor, photons: float | None = None, read_noise_e: float = 0.0,
            generator: torch.Generator | None = None) -> torch.Tensor:
        """The sensor's reading in command space, ``R s(phi + IF u)`` (nm): ``(rows, n_pupil)`` turbulent phase (nm)
        and ``(rows, K)`` applied commands (nm); photon and read noise as
        :meth:`~eofnn.sim.sensing.pyramid.PyramidSensor.measure` draws them."""
        residual = torch.as_tensor(phase, dtype=torch.float64) + self.surface(u)
        signals = self.sensor.measure(residual, photons, read_noise_e, generator)
        return signals @ self.reconstructor.to(signals).T

    def products(self, phase: np.ndarray, with_slopes: bool = False) -> dict[str, torch.Tensor]:
        """What scoring the loop needs of ``(rows, n_pupil)`` phase (nm): ``fit = P F phi`` and ``z = IF^T phi``
        (``(rows, K)``), and the pupil's ``sum phi`` and ``sum phi²`` (``(rows,)``); ``sensed``, the loop's truth in
        command space, is ``fit`` (the pyramid's reading is not linear in the phase: the loop reads the residual
        itself). ``with_slopes`` is refused in one line: the pyramid has none."""
        require(not with_slopes, "record 'slopes' is invalid with sensor.kind pyramid: it measures no slopes")
        phase = np.asarray(phase, dtype=np.float64)
        z = torch.as_tensor(np.ascontiguousarray((self.influence_t @ phase.T).T))
        fit = z @ self.fit_matrix.T
        return {"fit": fit, "sensed": fit, "z": z, "sum": torch.as_tensor(phase.sum(1)),
                "sumsq": torch.as_tensor(np.einsum("ij,ij->i", phase, phase))}

    def pupil_rms(self, z: torch.Tensor, total: torch.Tensor, total_sq: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Piston-removed RMS over the pupil of ``phi + IF u`` from :meth:`products`' ``z, sum, sumsq`` and the applied
        command ``u`` (``(..., K)``): ``(...)``."""
        return piston_removed_rms(self.gram, self.pupil_sums, self.n_pupil, z, total, total_sq, u)
