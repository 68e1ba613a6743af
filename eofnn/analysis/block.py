"""Stability of coupled (neighbourhood) linear filters: the block system and its spectral radius.

Each actuator's command reads its neighbours' histories, so ``D(z) y = N(z) u`` holds with ``K x K`` matrix
polynomials and the loop obeys ``P(z) = D(z) - g Q(z) N(z)`` (``Q`` the scalar plant polynomial of
:mod:`eofnn.analysis.stability`). ``P_0 = I``, so the loop is the recursion ``y(n) = -sum_k P_k y(n-k)``, whose
block companion matrix (sparse, ``K L x K L``) has the closed-loop poles as eigenvalues. Margins are found by
bracketing and bisecting its spectral radius (a pocket of instability between two bracketing points is missed).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from eofnn.analysis import polynomials as poly
from eofnn.errors import ConfigError

#: Dense eigenvalues up to this companion size, ARPACK beyond.
DENSE_LIMIT = 2500
#: Transfer functions (a K x K solve per frequency) up to this many actuators.
TRANSFER_LIMIT = 400
#: Largest block companion (rows: actuators x polynomial order) analysed. The margins take ~100 spectral radii;
#: ARPACK converges slowly on the clustered poles of thousands of similar loops (measured on 2 shared cores: 1264
#: actuators x 7 = 8848 rows in 8 s, 5024 x 5 = 25120 rows 100-130 s for *one* radius), so beyond this a coupled
#: analysis is refused up front (:class:`CoupledAnalysisTooLarge`) instead of running for hours.
COMPANION_LIMIT = 12000
GAIN_STEPS_UP = (1.02, 1.05, 1.1, 1.25, 1.5, 2.0, 3.0, 5.0, 10.0, 100.0)
GAIN_STEPS_DOWN = (0.98, 0.95, 0.9, 0.75, 0.5, 0.25, 0.1, 0.0, -0.1, -1.0, -10.0)
BISECTIONS = 30
#: The extra-delay scan's steps per frame (a crossing narrower than 1 / DELAY_SUBSTEPS frame may be missed).
DELAY_SUBSTEPS = 10


class CoupledAnalysisTooLarge(ConfigError):
    """A neighbourhood filter's coupled analysis is beyond :data:`COMPANION_LIMIT` (the message gives the size)."""


def companion_rows(n_actuators: int, kind: str, history_length: int, delay_frames: float,
                   controller_delay_frames: float) -> int:
    """Rows of the block companion of :func:`spectral_radius` for a coupled filter (its order times ``K``): the
    larger of ``D``'s order and the plant times ``N`` (one more frame for a fractional delay), as in
    :func:`characteristic`."""
    def lag(tau: float) -> int:
        return math.floor(tau) + (0 if float(tau).is_integer() else 1)
    d_order = history_length if kind == "closed_loop" else lag(controller_delay_frames) + history_length - 1
    return n_actuators * max(d_order, lag(delay_frames) + history_length - 1)


def require_coupled_size(n_actuators: int, kind: str, history_length: int, setup) -> None:
    """Refuse, up front, a coupled analysis whose companion exceeds :data:`COMPANION_LIMIT` rows."""
    rows = companion_rows(n_actuators, kind, history_length, setup.delay_frames, setup.controller_delay)
    if rows > COMPANION_LIMIT:
        raise CoupledAnalysisTooLarge(
            f"the coupled stability analysis of a neighbourhood filter on {n_actuators} actuators needs a "
            f"{rows}-row block companion (actuators x order), more than the {COMPANION_LIMIT} it handles in minutes "
            "(each margin takes about 100 sparse eigenvalue problems): analyse a per-actuator filter, or measure "
            "this one's DM-gain interval by simulation (compare --simulated_margins)")


def matrix_polynomials(weights: torch.Tensor, neighbours: torch.Tensor, kind: str, history_length: int,
                       dm_gain_model: float, controller_delay: float) -> tuple[list[sp.csr_matrix], list[sp.csr_matrix]]:
    """``(D, N)`` as lists of sparse ``K x K`` coefficient matrices of ``z^0, z^-1, ...``.

    An open-loop ``D`` is ``1 + g_model z^-d F W`` with ``F = (1 - f) + f z^-1`` for a fractional controller delay.
    """
    k_act, m_slots = neighbours.shape
    p = history_length
    taps = weights.shape[1] // m_slots
    w = weights.detach().to(torch.float64).cpu().numpy().reshape(k_act, m_slots, taps)
    nbr = neighbours.cpu().numpy()
    rows = np.repeat(np.arange(k_act)[:, None], m_slots, 1)
    inside = nbr < k_act  # off-pupil slots read zeros

    def matrix(values: np.ndarray) -> sp.csr_matrix:
        return sp.csr_matrix((values[inside], (rows[inside], nbr[inside])), shape=(k_act, k_act))

    eye = sp.identity(k_act, format="csr")
    if kind == "closed_loop":
        d_list = [eye] + [-matrix(w[:, :, j]) for j in range(p)]
        n_list = [matrix(w[:, :, p + j]) for j in range(p)]
    else:
        n_list = [matrix(w[:, :, j]) for j in range(p)]
        lag, fraction = math.floor(controller_delay), controller_delay - math.floor(controller_delay)
        d_list = [eye] + [sp.csr_matrix((k_act, k_act)) for _ in range(lag + p - 1 + (1 if fraction else 0))]
        for j, f_j in enumerate(n_list):
            if not fraction:
                d_list[lag + j] = d_list[lag + j] + dm_gain_model * f_j
            else:
                d_list[lag + j] = d_list[lag + j] + (1 - fraction) * dm_gain_model * f_j
                d_list[lag + j + 1] = d_list[lag + j + 1] + fraction * dm_gain_model * f_j
    return d_list, n_list


def characteristic(d_list: list, n_list: list, plant: np.ndarray, dm_gain: float) -> list[sp.csr_matrix]:
    """``P_k`` of ``P = D - g Q N`` for the plant polynomial coefficients ``plant`` (``Q``)."""
    k_act = d_list[0].shape[0]
    out = [sp.csr_matrix((k_act, k_act)) for _ in range(max(len(d_list), len(n_list) + len(plant) - 1))]
    for k, d_k in enumerate(d_list):
        out[k] = out[k] + d_k
    for i, q_i in enumerate(plant):
        if q_i:
            for j, n_j in enumerate(n_list):
                out[i + j] = out[i + j] - dm_gain * q_i * n_j
    while len(out) > 1 and out[-1].nnz == 0:
        out.pop()
    return out


def spectral_radius(p_list: list[sp.csr_matrix]) -> float:
    """Largest pole modulus of the recursion ``sum_k P_k y(n-k) = 0`` (``P_0 = I``)."""
    k_act, order = p_list[0].shape[0], len(p_list) - 1
    if order == 0:
        return 0.0
    blocks = [[None] * order for _ in range(order)]
    for k in range(order):
        blocks[0][k] = -p_list[k + 1]
    for k in range(1, order):
        blocks[k][k - 1] = sp.identity(k_act, format="csr")
    companion = sp.bmat(blocks, format="csr")
    if companion.shape[0] <= DENSE_LIMIT:
        return float(np.abs(np.linalg.eigvals(companion.toarray())).max())
    try:
        values = spla.eigs(companion, k=6, which="LM", return_eigenvectors=False, tol=1e-10, maxiter=20000)
    except spla.ArpackNoConvergence as err:  # use what converged
        values = err.eigenvalues
    return float(np.abs(values).max())


def block_analysis(weights: torch.Tensor, neighbours: torch.Tensor, kind: str, history_length: int, setup,
                   frequencies_hz: torch.Tensor) -> tuple:
    """Fields of a one-group :class:`~eofnn.analysis.stability.StabilityResult` for the coupled system."""
    require_coupled_size(neighbours.shape[0], kind, history_length, setup)
    d_list, n_list = matrix_polynomials(weights, neighbours, kind, history_length, setup.dm_gain_model,
                                        setup.controller_delay)

    def radius(dm_gain: float, delay_frames: float) -> float:
        plant = setup.plant_polynomial(delay_frames).numpy()
        return spectral_radius(characteristic(d_list, n_list, plant, dm_gain))

    g, tau = setup.dm_gain, float(setup.delay_frames)
    modulus = radius(g, tau)
    nan2 = torch.full((1, 2), math.nan, dtype=torch.float64)
    interval, delay_margin, integer = nan2.clone(), math.nan, -1
    if modulus < 1:
        stable_at = lambda gain: radius(gain, tau) < 1  # noqa: E731
        lower = _bisect_edge(stable_at, g, [g * s if g else s - 1 for s in GAIN_STEPS_DOWN])
        upper = _bisect_edge(stable_at, g, [g * s if g else s - 1 for s in GAIN_STEPS_UP])
        interval = torch.tensor([[lower, upper]], dtype=torch.float64)
        known: dict[float, bool] = {}

        def stable_with(delay: float) -> bool:
            if delay not in known:
                known[delay] = radius(g, delay) < 1
            return known[delay]

        integer = next((j - 1 for j in range(1, setup.max_extra_delay_frames + 1) if not stable_with(tau + j)),
                       setup.max_extra_delay_frames)
        # Stability is not monotone in a fractional delay (the plant interpolates between two whole lags): scan in
        # steps of 1 / DELAY_SUBSTEPS frame up to the first unstable delay, then bisect.
        steps = [tau + k / DELAY_SUBSTEPS for k in range(1, DELAY_SUBSTEPS * setup.max_extra_delay_frames + 1)]
        delay_margin = _bisect_edge(stable_with, tau, steps) - tau
    freqs = frequencies_hz
    rejection = noise = torch.zeros(1, 0, dtype=torch.complex128)
    if neighbours.shape[0] <= TRANSFER_LIMIT:
        rejection, noise = _mean_diagonal_transfer(d_list, n_list, setup, freqs)
    else:
        freqs = freqs[:0]
    return (torch.tensor([modulus], dtype=torch.float64), interval, nan2.clone(),
            torch.tensor([delay_margin], dtype=torch.float64), torch.tensor([integer]), freqs, rejection, noise)


def _bisect_edge(stable_at, inside: float, candidates: list[float]) -> float:
    """Edge of the stable set from ``inside`` towards the first unstable candidate (``+-inf`` if none is)."""
    previous = inside
    for candidate in candidates:
        if not stable_at(candidate):
            lo, hi = previous, candidate
            for _ in range(BISECTIONS):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if stable_at(mid) else (lo, mid)
            return 0.5 * (lo + hi)
        previous = candidate
    return math.inf if candidates[-1] > inside else -math.inf


def _mean_diagonal_transfer(d_list, n_list, setup, frequencies_hz) -> tuple[torch.Tensor, torch.Tensor]:
    """Rejection and noise transfer of an actuator to its own input, averaged over actuators (dense solves)."""
    omega = 2 * math.pi * frequencies_hz.numpy() / setup.frame_rate_hz
    plant = setup.plant_polynomial().numpy()
    p_list = characteristic(d_list, n_list, plant, setup.dm_gain)
    delay_dm = poly.fractional_delay(setup.delay_frames).numpy()

    def at(mats, z_inv):
        return sum(m.toarray() * z_inv ** k for k, m in enumerate(mats))

    rejection, noise = [], []
    for w in omega:
        z_inv = np.exp(-1j * w)
        p_value = at(p_list, z_inv)
        dm = sum(c * z_inv ** k for k, c in enumerate(delay_dm))
        s_matrix = np.linalg.solve(p_value, at(d_list, z_inv))
        n_matrix = np.linalg.solve(p_value, setup.dm_gain * dm * at(n_list, z_inv))
        rejection.append(np.diagonal(s_matrix).mean())
        noise.append(np.diagonal(n_matrix).mean())
    return (torch.tensor(np.array(rejection))[None], torch.tensor(np.array(noise))[None])
