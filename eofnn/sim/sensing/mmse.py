"""A noise-aware (MMSE / MAP) Shack-Hartmann reconstructor in command space (``sensor.reconstructor: mmse``).

``R = C_ys (C_ss + C_n)^-1`` (Wallner 1983; Ellerbroek 2002): the linear estimate of ``y_fit = F phi``, the DM's
least-squares fit of the phase over the pupil (``F = (G + ridge)^-1 IF_p^T``, :mod:`eofnn.sim.sensing.pupil`), that
minimises ``E|y_fit - R s|²`` for slopes ``s = S phi + n``, with

- ``C_ss = S C_phi S^T`` and ``C_ys = F C_phi S^T``, ``C_phi`` von Kármán's phase covariance between the sensor's
  fine points: the slopes' covariance *with* the aliasing of the phase the DM cannot fit, which a command-space prior
  ``C D^T (D C D^T + C_n)^-1`` leaves out (then aliasing passes as signal). Its ``r0`` and ``L0`` are the scenario's
  atmosphere's: knowledge a simulation has; a real system identifies them from its telemetry. Piston, tip and tilt
  over the fine grid leave the prior when the atmosphere removes them from its screens (``remove_ptt``);
- ``C_n`` the slope noise covariance (nm²): the sensor's white noise per slope (photon and read noise of the
  detector, the plant's ``wfs_noise_nm``), scaled per slope for partly lit subapertures.

``C_phi`` depends only on the offset between two points of the fine lattice, so it is a table of offsets, and the
products are accumulated a block of points at a time. Unlike the truncated least-squares reconstructor,
``P = R D`` is not a projector: every mode is kept, each weighted by what the prior and the noise say of it.
"""

from __future__ import annotations

import math

import numpy as np

from eofnn.validation import Interval, check_value

#: The noise variance floor (fraction of the mean slope variance ``trace(D C D^T) / n_slopes``) that keeps a
#: noise-free sensor's MMSE reconstructor well posed (modes the slopes cannot see have no information then).
NOISE_FLOOR = 1e-6


def von_karman_covariance_nm2(r_m: np.ndarray, r0_m: float, outer_scale_m: float, wavelength_m: float) -> np.ndarray:
    """Von Kármán's phase covariance at separations ``r_m`` (m), as OPD (nm²), ``r0_m`` given at ``wavelength_m``.

    ``B(r) = (L0 / r0)^(5/3) Γ(11/6) / (2^(5/6) π^(8/3)) (24/5 Γ(6/5))^(5/6) u^(5/6) K_(5/6)(u)``, ``u = 2 π r / L0``
    (rad²; its limit at ``r = 0`` for ``u = 0``), times ``(λ / 2π)²``.
    """
    from scipy.special import gamma, kv

    check_value("r0_m", r0_m, Interval(0, None, closed="neither", unit="m"))
    check_value("outer_scale_m", outer_scale_m, Interval(0, None, closed="neither", unit="m"))
    c = ((outer_scale_m / r0_m) ** (5 / 3) * gamma(11 / 6) / (2 ** (5 / 6) * math.pi ** (8 / 3))
         * (24 / 5 * gamma(6 / 5)) ** (5 / 6))
    u = 2 * math.pi * np.asarray(r_m, dtype=np.float64) / outer_scale_m
    zero = u < 1e-12
    safe = np.where(zero, 1.0, u)
    value = np.where(zero, 2 ** (-1 / 6) * gamma(5 / 6), safe ** (5 / 6) * kv(5 / 6, safe))
    return c * value * (wavelength_m * 1e9 / (2 * math.pi)) ** 2


def slope_covariances(slope_operator, fit_rows, in_pupil: np.ndarray, lattice: np.ndarray, covariance_table: np.ndarray,
                       block: int = 512, removed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(C_ss, C_ys)``: ``S C_phi S^T`` ``(n_slopes, n_slopes)`` and ``F C_phi S^T`` ``(K, n_slopes)`` (nm²).

    Parameters
    ----------
    slope_operator : scipy.sparse matrix
        ``S`` ``(n_slopes, n_fine)``.
    fit_rows : scipy.sparse matrix or ndarray
        ``IF_p^T`` ``(K, N_p)``: the influence functions at the fine points inside the pupil (``F = (G + ridge)^-1``
        times it is applied by the caller).
    in_pupil : ndarray
        Boolean ``(n_fine,)``: the fine points inside the pupil (``N_p`` of them, in order).
    lattice : ndarray
        ``(n_fine, 2)`` integer (column, row) indices of the fine points on their lattice.
    covariance_table : ndarray
        ``B[|di|, |dj|]`` (nm²): the phase covariance at a lattice offset.
    block : int
        Fine points per block of the covariance (memory: three ``block x n_points`` arrays).
    removed : ndarray or None
        ``(n_fine, m)`` orthonormal modes removed from every phase screen (piston, tip and tilt over the fine grid):
        the covariance is then ``(I - Q Q^T) C_phi (I - Q Q^T)``.
    """
    import scipy.sparse as sp

    s = sp.csc_matrix(slope_operator)
    edges = np.flatnonzero(np.diff(s.indptr))  # the fine points the slopes read
    s_edges_t = s[:, edges].T.tocsr()  # (n_e, n_slopes)
    pupil = np.flatnonzero(in_pupil)
    fit = sp.csr_matrix(fit_rows)

    def against_edges(points: np.ndarray) -> np.ndarray:  # C_phi(points, edges) S_e^T: (len(points), n_slopes)
        di = np.abs(lattice[points, None, 0] - lattice[None, edges, 0])
        dj = np.abs(lattice[points, None, 1] - lattice[None, edges, 1])
        return np.asarray(s_edges_t.T.dot(covariance_table[di, dj].T).T)

    n_slopes = s.shape[0]
    c_ss = np.zeros((n_slopes, n_slopes))
    for lo in range(0, len(edges), block):
        part = np.arange(lo, min(lo + block, len(edges)))
        c_ss += np.asarray(s_edges_t[part].T @ against_edges(edges[part]))
    c_ys = np.zeros((fit.shape[0], n_slopes))
    for lo in range(0, len(pupil), block):
        part = np.arange(lo, min(lo + block, len(pupil)))
        c_ys += np.asarray(fit[:, part] @ against_edges(pupil[part]))
    if removed is not None:  # C' = C - C Q Q^T - Q Q^T C + Q (Q^T C Q) Q^T
        q = np.asarray(removed, dtype=np.float64)
        cq = np.zeros_like(q)
        for lo in range(0, len(q), block):
            rows = np.arange(lo, min(lo + block, len(q)))
            di = np.abs(lattice[rows, None, 0] - lattice[None, :, 0])
            dj = np.abs(lattice[rows, None, 1] - lattice[None, :, 1])
            cq[rows] = covariance_table[di, dj] @ q
        a, b = np.asarray(s @ cq), np.asarray(s @ q)  # S C Q, S Q: (n_slopes, m)
        x, y = np.asarray(fit @ cq[pupil]), np.asarray(fit @ q[pupil])  # F' C Q, F' Q: (K, m)
        qcq = q.T @ cq
        c_ss = c_ss - a @ b.T - b @ a.T + b @ qcq @ b.T
        c_ys = c_ys - x @ b.T - y @ a.T + y @ qcq @ b.T
    return 0.5 * (c_ss + c_ss.T), c_ys


def mmse_reconstructor(signal_nm2: np.ndarray, cross_nm2: np.ndarray, slope_noise_nm: float,
                       slope_noise_scale: np.ndarray | None = None) -> np.ndarray:
    """``R = C_ys (C_ss + C_n)^-1`` ``(K, n_slopes)`` (module docstring).

    Parameters
    ----------
    signal_nm2 : ndarray
        ``C_ss`` ``(n_slopes, n_slopes)``: the noise-free slopes' covariance (nm²).
    cross_nm2 : ndarray
        ``C_ys`` ``(K, n_slopes)``: the commands' covariance with the slopes (nm²).
    slope_noise_nm : float
        RMS white noise of a fully lit subaperture's slope (nm), at least 0; the variance is floored at
        :data:`NOISE_FLOOR` of the mean slope variance.
    slope_noise_scale : ndarray or None
        ``(n_slopes,)`` each slope's noise RMS relative to a fully lit one's (``None``: all ones).
    """
    check_value("slope_noise_nm", slope_noise_nm, Interval(0, None, unit="nm RMS per slope"))
    total = np.array(signal_nm2, dtype=np.float64)
    scale = np.ones(len(total)) if slope_noise_scale is None else np.asarray(slope_noise_scale, dtype=np.float64)
    variance = max(slope_noise_nm ** 2, NOISE_FLOOR * float(np.trace(total)) / len(total))
    total[np.diag_indices_from(total)] += variance * scale ** 2
    from scipy.linalg import cho_factor, cho_solve

    # C_ss + C_n is symmetric positive definite: R^T = (C_ss + C_n)^-1 C_ys^T.
    return cho_solve(cho_factor(total), np.asarray(cross_nm2, dtype=np.float64).T).T


def loop_mmse_reconstructor(operators, atmosphere, slope_noise_nm: float) -> np.ndarray:
    """The MMSE reconstructor ``(K, 2 n_sub)`` of a Shack-Hartmann's loop operators
    (:class:`~eofnn.sim.sensing.pupil.LoopOperators`) for ``atmosphere``'s von Kármán statistics (its ``r0_m``,
    ``outer_scale_m``, ``r0_wavelength_m``; piston, tip and tilt out of the prior when its screens remove them) and
    white slope noise of RMS ``slope_noise_nm`` (nm) scaled per slope as partly lit subapertures have it:
    ``R = C_ys (C_ss + C_n)^-1`` with ``C_ys = F C_phi S^T``, ``F`` the DM's fit of the phase over the pupil."""
    geometry = operators.sensor.geometry
    h = geometry.fine_pitch_m
    lattice = np.rint((geometry.fine_positions_m - geometry.fine_positions_m.min(0)) / h).astype(np.int64)
    n = int(lattice.max()) + 1
    offsets = np.hypot(*np.meshgrid(np.arange(n), np.arange(n), indexing="ij")) * h
    table = von_karman_covariance_nm2(offsets, atmosphere.r0_m, atmosphere.outer_scale_m, atmosphere.r0_wavelength_m)
    removed = geometry.fine_grid.ptt_basis() if atmosphere.remove_ptt else None  # as the screens are made
    signal, cross = slope_covariances(geometry.slope_operator, operators.influence_pupil_t, operators.pupil, lattice,
                                      table, removed=removed)
    gram = operators.gram.toarray()  # C_ys = F C_phi S^T with F = (G + ridge)^-1 IF_p^T, the pupil's ridge
    cross = np.linalg.solve(gram + 1e-10 * np.diag(gram).max() * np.eye(len(gram)), cross)
    return mmse_reconstructor(signal, cross, slope_noise_nm, operators.sensor.slope_noise_scale)
