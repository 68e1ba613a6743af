"""A Shack-Hartmann's operators as the loop uses them: commands in nm of surface, the pupil's fit of the phase, and
the residual over the pupil from a few numbers per frame (:mod:`eofnn.sim.loop.sensing` runs the loop with them).

Commands are in nm of DM surface for a smooth shape: OOPAO's peak-1 Gaussian influence functions overlap (a uniform
command of 1 nm is a 3.0 nm surface at coupling 0.35), so they are divided by their lattice sum
``(sum_j coupling^(j²))²``; ``R`` is multiplied by it and ``D`` divided by it (the interaction matrix in the loop's
command units, slopes in nm per nm of command), so ``P = R D`` does not change.

The residual over the pupil, ``r = phi + IF u`` on the ``N_p`` fine points inside the pupil (``u`` the applied DM
command), is never formed in the loop: with ``z = IF_p^T phi_p``, ``G = IF_p^T IF_p`` and ``b = IF_p^T 1``,
``sum r² = sum phi_p² + 2 z.u + u.G u`` and ``sum r = sum phi_p + b.u``, so its piston-removed RMS
``sqrt(mean r² - (mean r)²)`` needs two numbers and ``z`` per frame (``z`` also gives the fit
``P (G + ridge)^-1 z``: the least-squares DM fit of the phase over the pupil on the modes the sensor sees).
"""

from __future__ import annotations

import numpy as np

from eofnn.lazy import lazy_module
from eofnn.sim.sensing.least_squares import surface_per_command
from eofnn.sim.sensing.shack_hartmann import ShackHartmannSensor

torch = lazy_module("torch")



def piston_removed_rms(gram, pupil_sums: torch.Tensor, n_pupil: int, z: torch.Tensor, total: torch.Tensor,
                       total_sq: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Piston-removed RMS over ``n_pupil`` pupil points of ``phi + IF u``, ``(...)``, without forming it: from ``z =
    IF^T phi`` ``(..., K)``, the pupil's ``sum phi`` and ``sum phi²`` ``(...)``, the applied commands ``u`` ``(..., K)``,
    the influence functions' Gram matrix ``G = IF^T IF`` over the pupil (sparse, symmetric) and their sums over it
    ``(K,)``."""
    flat = u.reshape(-1, u.shape[-1])
    gu = torch.as_tensor(np.asarray((gram @ flat.numpy().T).T)).reshape(u.shape)  # G symmetric
    mean_sq = (total_sq + 2 * (z * u).sum(-1) + (u * gu).sum(-1)) / n_pupil
    mean = (total + u @ pupil_sums) / n_pupil
    return (mean_sq - mean * mean).clamp(min=0).sqrt()


def transposed(values: torch.Tensor) -> np.ndarray:
    """``values.T`` ``(columns, rows)`` as a C-contiguous array: the dense factor of a scipy sparse product, which reads
    it so and otherwise copies a transposed view element by element (numpy's strided copy, several times slower than
    torch's blocked transpose on a chunk's fine-grid phase). The same numbers, copied faster."""
    return values.T.contiguous().numpy()


class LoopOperators:
    """A built :class:`ShackHartmannSensor` with the loop's operators (module docstring).

    Attributes
    ----------
    surface_per_command : float
        The lattice sum the influence functions are divided by.
    reconstructor, interaction_matrix, projector, fit_matrix : Tensor
        ``R`` ``(K, 2 n_sub)`` (nm of command per nm of slope), ``D`` ``(2 n_sub, K)`` (nm of slope per nm of command),
        ``P = R D`` ``(K, K)``, ``P (G + ridge)^-1`` ``(K, K)``.
    gram : scipy.sparse.csr_matrix
        ``G`` ``(K, K)``, banded (influence functions reach 3.6 pitches).
    """

    def __init__(self, sensor: ShackHartmannSensor) -> None:
        self.sensor = sensor
        geometry = sensor.geometry
        self.pupil = geometry.fine_in_pupil
        self.n_pupil = int(self.pupil.sum())
        self.surface_per_command = surface_per_command(sensor.config.mechanical_coupling)
        influence = (sensor.influence / self.surface_per_command).tocsr()
        self.influence_pupil_t = influence[self.pupil].T.tocsr()  # IF_p^T (K, N_p)
        gram_sparse = (self.influence_pupil_t @ self.influence_pupil_t.T).tocsr()  # banded: 7 pitches across
        self.gram = gram_sparse
        gram = gram_sparse.toarray()
        self.pupil_sums = torch.as_tensor(np.asarray(self.influence_pupil_t.sum(axis=1)).ravel())  # b
        self.reconstructor = torch.as_tensor(sensor.reconstructor * self.surface_per_command)
        self.interaction_matrix = torch.as_tensor(sensor.interaction_matrix / self.surface_per_command)
        self.projector = torch.as_tensor(sensor.reconstructor @ sensor.interaction_matrix)
        # A tiny ridge keeps the Gram matrix of actuators whose influence barely reaches the pupil invertible.
        ridge = 1e-10 * np.diag(gram).max() * np.eye(len(gram))
        self.fit_matrix = self.projector @ torch.as_tensor(np.linalg.inv(gram + ridge))
        self.slopes_t = geometry.slope_operator.T.tocsr()
        self.influence_t = influence.T.tocsr()

    def products(self, phase: np.ndarray, with_slopes: bool = False, with_fit: bool = True) -> dict[str, torch.Tensor]:
        """What the loop needs of ``(rows, n_fine)`` phase (nm): ``fit = P F phi``, ``sensed = R S phi`` (``(rows, K)``),
        ``z`` ``(rows, K)`` and the pupil's ``sum phi`` and ``sum phi²`` (``(rows,)``); ``with_slopes`` adds ``slopes = S phi``
        ``(rows, 2 n_sub)`` (what recording slopes needs; the other products are the same numbers either way);
        ``with_fit=False`` leaves ``fit`` out (:meth:`fit` makes it of ``z`` later, to the same numbers)."""
        columns = transposed(torch.from_numpy(phase))  # phase.T
        inside = phase[:, self.pupil]
        z = torch.as_tensor(np.ascontiguousarray((self.influence_pupil_t @ columns[self.pupil]).T))
        slopes = torch.as_tensor(np.asarray((self.slopes_t.T @ columns).T))  # phase @ S^T, as scipy computes it
        out = {"sensed": slopes @ self.reconstructor.T, "z": z,
               "sum": torch.as_tensor(inside.sum(1)), "sumsq": torch.as_tensor(np.einsum("ij,ij->i", inside, inside))}
        if with_fit:
            out["fit"] = self.fit(z)
        return {**out, "slopes": slopes} if with_slopes else out

    def fit(self, z: torch.Tensor) -> torch.Tensor:
        """``P F phi`` ``(rows, K)`` of :meth:`products`' ``z`` ``(rows, K)``: the DM's fit of the phase."""
        return z @ self.fit_matrix.T

    def pupil_rms(self, z: torch.Tensor, total: torch.Tensor, total_sq: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Piston-removed RMS over the pupil of ``phi + IF u`` from :meth:`products`' ``z, sum, sumsq`` and the applied
        command ``u`` (``(..., K)``): ``(...)``."""
        return piston_removed_rms(self.gram, self.pupil_sums, self.n_pupil, z, total, total_sq, u)

    def surface(self, u: torch.Tensor) -> torch.Tensor:
        """``IF u``: the DM surface (nm) on every fine point for ``(rows, K)`` commands."""
        return torch.as_tensor(np.asarray(u.numpy() @ self.influence_t))
