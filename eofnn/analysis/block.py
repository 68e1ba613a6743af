"""Stability of coupled (neighbourhood) linear filters: the block system and its spectral radius.

Each actuator's command reads its neighbours' histories, so ``D(z) y = N(z) u`` holds with ``K x K`` matrix
polynomials and the loop obeys ``P(z) = D(z) - g Q(z) N(z)`` (``Q`` the scalar plant polynomial of
:mod:`eofnn.analysis.stability`). ``P_0 = I``, so the loop is the recursion ``y(n) = -sum_k P_k y(n-k)``, whose
block companion matrix (sparse, ``K L x K L``) has the closed-loop poles as eigenvalues. Margins are found by
bracketing its spectral radius ``rho`` (a pocket of instability between two bracketing points is missed), then:

- up to :data:`DENSE_LIMIT` rows, every eigenvalue (LAPACK) and a bisection of stable / unstable;
- beyond, the few largest eigenvalues (ARPACK), each solve started from the previous one's dominant eigenvector, and
  Brent's method on ``rho - 1``, which is continuous in the DM gain and the delay: five to seven radii per edge once
  bracketed, where bisection takes thirty, and those near the edge, where the critical pole stands apart, converge
  fastest. At 40 across (1264 actuators) the poles of a 10-tap open-loop neighbourhood filter well inside the stable
  range form a ring of thousands of nearly equal moduli, on which ARPACK's defaults (6 eigenvalues, a Krylov space
  of 20) were slow per radius, or did not converge.

How long it takes (``experiments/coupled_margins.py``, the benchmark's ``coupled/1264x10`` row): ``docs/findings.md``.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from scipy.optimize import brentq
from threadpoolctl import threadpool_limits

from eofnn.analysis import polynomials as poly
from eofnn.errors import ConfigError
from eofnn.resources import require_memory

#: Dense eigenvalues (and bisected edges) up to this companion size, ARPACK (and Brent's method) beyond.
DENSE_LIMIT = 2500
#: Transfer functions (a K x K solve per frequency) up to this many actuators.
TRANSFER_LIMIT = 400
#: ARPACK's eigenvalues of largest modulus asked for, its Krylov space, its relative tolerance and the seed of the
#: first start vector, chosen on the ring of poles above (the alternatives tried: ``docs/findings.md``).
ARPACK_EIGENVALUES, ARPACK_KRYLOV, ARPACK_TOL, ARPACK_SEED = 10, 60, 1e-10, 0
#: Brent's method stops when an edge is known to this fraction of its bracket (bisection: 30 halvings, 5e-10).
EDGE_TOLERANCE = 1e-10
#: Largest block companion (rows: actuators x polynomial order) analysed: 40 across with up to 13 taps; a radius
#: costs more than linearly in the rows (the timings: ``docs/findings.md``), so beyond, the analysis is refused up
#: front (:class:`CoupledAnalysisTooLarge`). Raise this to analyse an ELT's filter (and rerun the ELT runs of
#: experiments/README.md, which say their neighbourhood filters were refused).
COMPANION_LIMIT = 20000
GAIN_STEPS_UP = (1.02, 1.05, 1.1, 1.25, 1.5, 2.0, 3.0, 5.0, 10.0, 100.0)
GAIN_STEPS_DOWN = (0.98, 0.95, 0.9, 0.75, 0.5, 0.25, 0.1, 0.0, -0.1, -1.0, -10.0)
BISECTIONS = 30
#: The extra-delay scan's steps per frame (a crossing narrower than 1 / DELAY_SUBSTEPS frame may be missed).
DELAY_SUBSTEPS = 10


class CoupledAnalysisUnavailable(ConfigError):
    """A neighbourhood filter has no analytic margins (the message says why): reported like a network's."""


class CoupledAnalysisTooLarge(CoupledAnalysisUnavailable):
    """A neighbourhood filter's coupled analysis is beyond :data:`COMPANION_LIMIT` or the memory available (the
    message gives the size)."""


class CoupledAnalysisNotConverged(CoupledAnalysisUnavailable):
    """ARPACK found no eigenvalue of a companion, even in a larger Krylov space."""


def companion_rows(n_actuators: int, kind: str, history_length: int, delay_frames: float,
                   controller_delay_frames: float) -> int:
    """Rows of the block companion of :func:`spectral_radius` for a coupled filter (its order times ``K``): the
    larger of ``D``'s order and the plant times ``N`` (one more frame for a fractional delay), as in
    :func:`characteristic`."""
    def lag(tau: float) -> int:
        return math.floor(tau) + (0 if float(tau).is_integer() else 1)
    d_order = history_length if kind == "closed_loop" else lag(controller_delay_frames) + history_length - 1
    return n_actuators * max(d_order, lag(delay_frames) + history_length - 1)


def coupled_bytes(rows: int, slots: int, n_actuators: int) -> int:
    """Memory (bytes) of the spectral radii of a ``rows``-row block companion whose ``K = n_actuators`` rows of
    coefficients hold ``slots`` neighbours each: the dense matrix and LAPACK's copy and workspace up to
    :data:`DENSE_LIMIT` rows; beyond, the sparse companion (its COO and CSR forms while it is built) and ARPACK's
    Krylov basis, work arrays and eigenvectors."""
    if rows <= DENSE_LIMIT:
        return 3 * 8 * rows * rows
    nonzeros = n_actuators * slots * (rows // max(n_actuators, 1)) + rows
    return 40 * nonzeros + 16 * rows * (ARPACK_KRYLOV + 2 * ARPACK_EIGENVALUES + 6)


def require_coupled_size(n_actuators: int, kind: str, history_length: int, setup, slots: int = 9) -> None:
    """Refuse, up front, a coupled analysis whose companion exceeds :data:`COMPANION_LIMIT` rows, or whose largest
    companion (the delay scan's, ``max_extra_delay_frames`` on) does not fit the memory available (one line each)."""
    rows = companion_rows(n_actuators, kind, history_length, setup.delay_frames, setup.controller_delay)
    if rows > COMPANION_LIMIT:
        raise CoupledAnalysisTooLarge(
            f"the coupled stability analysis of a neighbourhood filter on {n_actuators} actuators needs a "
            f"{rows}-row block companion (actuators x order), more than the {COMPANION_LIMIT} it handles in minutes "
            "(the margins take 30-40 sparse eigenvalue problems, each slower as the companion grows): analyse a "
            "per-actuator filter, or measure this one's DM-gain interval by simulation (compare --simulated_margins)")
    longest = companion_rows(n_actuators, kind, history_length, setup.delay_frames + setup.max_extra_delay_frames,
                             setup.controller_delay)
    try:
        require_memory(coupled_bytes(longest, slots, n_actuators),
                       f"the coupled stability analysis of a neighbourhood filter on {n_actuators} actuators "
                       f"({slots} neighbours each, block companions up to {longest} rows)")
    except ConfigError as err:
        raise CoupledAnalysisTooLarge(str(err)) from None


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


def companion(p_list: list[sp.csr_matrix]) -> sp.csr_matrix | None:
    """The block companion matrix of the recursion ``sum_k P_k y(n-k) = 0`` (``P_0 = I``; ``None`` for order 0)."""
    k_act, order = p_list[0].shape[0], len(p_list) - 1
    if order == 0:
        return None
    blocks = [[None] * order for _ in range(order)]
    for k in range(order):
        blocks[0][k] = -p_list[k + 1]
    for k in range(1, order):
        blocks[k][k - 1] = sp.identity(k_act, format="csr")
    return sp.bmat(blocks, format="csr")


def spectral_radius(p_list: list[sp.csr_matrix]) -> float:
    """Largest pole modulus of the recursion ``sum_k P_k y(n-k) = 0`` (``P_0 = I``)."""
    return SpectralRadius()(p_list)


class SpectralRadius:
    """:func:`spectral_radius`, called again and again on nearby systems: every eigenvalue up to
    :data:`DENSE_LIMIT` rows; beyond, ARPACK's :data:`ARPACK_EIGENVALUES` of largest modulus, started from the
    previous call's dominant eigenvector when the companion has the same size (a seeded random vector otherwise, so
    a sequence of calls is reproducible)."""

    def __init__(self) -> None:
        self._start: np.ndarray | None = None

    def __call__(self, p_list: list[sp.csr_matrix]) -> float:
        matrix = companion(p_list)
        if matrix is None:
            return 0.0
        rows = matrix.shape[0]
        if rows <= DENSE_LIMIT:
            return float(np.abs(np.linalg.eigvals(matrix.toarray())).max())
        start = self._start
        if start is None or len(start) != rows:
            start = np.random.default_rng(ARPACK_SEED).standard_normal(rows)
        values, vectors = _largest_eigenvalues(matrix, start, ARPACK_KRYLOV)
        if not len(values):  # none converged: a larger Krylov space, from a fresh start
            values, vectors = _largest_eigenvalues(matrix, np.random.default_rng(ARPACK_SEED).standard_normal(rows),
                                                   2 * ARPACK_KRYLOV)
        if not len(values):
            raise CoupledAnalysisNotConverged(
                f"the spectral radius of a {rows}-row block companion did not converge (ARPACK, {ARPACK_EIGENVALUES} "
                f"eigenvalues, Krylov spaces of {ARPACK_KRYLOV} and {2 * ARPACK_KRYLOV}): measure this filter's "
                "DM-gain interval by simulation (compare --simulated_margins)")
        largest = int(np.abs(values).argmax())
        # A real start vector in the dominant (complex pair's) invariant plane.
        self._start = vectors[:, largest].real + vectors[:, largest].imag
        return float(np.abs(values[largest]))


def _largest_eigenvalues(matrix: sp.csr_matrix, start: np.ndarray, krylov: int) -> tuple[np.ndarray, np.ndarray]:
    """ARPACK's :data:`ARPACK_EIGENVALUES` of largest modulus and their eigenvectors (those that converged), on one
    BLAS thread: its thousands of small products (a Krylov basis of ``rows x krylov``) gain nothing from threads, and
    on a busy machine threaded BLAS was far slower (``docs/findings.md``)."""
    with threadpool_limits(1, user_api="blas"):
        try:
            return spla.eigs(matrix, k=ARPACK_EIGENVALUES, ncv=min(krylov, matrix.shape[0]), which="LM", v0=start,
                             tol=ARPACK_TOL, maxiter=20000)
        except spla.ArpackNoConvergence as err:  # use what converged
            return err.eigenvalues, err.eigenvectors


def block_analysis(weights: torch.Tensor, neighbours: torch.Tensor, kind: str, history_length: int, setup,
                   frequencies_hz: torch.Tensor, delay_margin: bool = True) -> tuple:
    """Fields of a one-group :class:`~eofnn.analysis.stability.StabilityResult` for the coupled system (without
    ``delay_margin``, the delay margins are left undefined: NaN and -1)."""
    k_act, slots = neighbours.shape
    require_coupled_size(k_act, kind, history_length, setup, slots)
    d_list, n_list = matrix_polynomials(weights, neighbours, kind, history_length, setup.dm_gain_model,
                                        setup.controller_delay)
    # Up to DENSE_LIMIT rows every eigenvalue and bisected edges, as always; beyond, ARPACK and Brent's method.
    bisect = companion_rows(k_act, kind, history_length, setup.delay_frames, setup.controller_delay) <= DENSE_LIMIT
    spectral, known = SpectralRadius(), {}

    def radius(dm_gain: float, delay_frames: float) -> float:
        if (dm_gain, delay_frames) not in known:
            plant = setup.plant_polynomial(delay_frames).numpy()
            known[dm_gain, delay_frames] = spectral(characteristic(d_list, n_list, plant, dm_gain))
        return known[dm_gain, delay_frames]

    g, tau = setup.dm_gain, float(setup.delay_frames)
    modulus = radius(g, tau)
    nan2 = torch.full((1, 2), math.nan, dtype=torch.float64)
    interval, margin, integer = nan2.clone(), math.nan, -1
    if modulus < 1:
        at_gain = lambda gain: radius(gain, tau)  # noqa: E731
        lower = _edge(at_gain, g, [g * s if g else s - 1 for s in GAIN_STEPS_DOWN], bisect)
        upper = _edge(at_gain, g, [g * s if g else s - 1 for s in GAIN_STEPS_UP], bisect)
        interval = torch.tensor([[lower, upper]], dtype=torch.float64)
    if modulus < 1 and delay_margin:
        at_delay = lambda delay: radius(g, delay)  # noqa: E731
        integer = next((j - 1 for j in range(1, setup.max_extra_delay_frames + 1) if not at_delay(tau + j) < 1),
                       setup.max_extra_delay_frames)
        # Stability is not monotone in a fractional delay (the plant interpolates between two whole lags): scan in
        # steps of 1 / DELAY_SUBSTEPS frame up to the first unstable delay, then refine.
        steps = [tau + k / DELAY_SUBSTEPS for k in range(1, DELAY_SUBSTEPS * setup.max_extra_delay_frames + 1)]
        margin = _edge(at_delay, tau, steps, bisect) - tau
    freqs = frequencies_hz
    rejection = noise = torch.zeros(1, 0, dtype=torch.complex128)
    if k_act <= TRANSFER_LIMIT:
        rejection, noise = _mean_diagonal_transfer(d_list, n_list, setup, freqs)
    else:
        freqs = freqs[:0]
    return (torch.tensor([modulus], dtype=torch.float64), interval, nan2.clone(),
            torch.tensor([margin], dtype=torch.float64), torch.tensor([integer]), freqs, rejection, noise)


def _edge(radius_at, inside: float, candidates: list[float], bisect: bool) -> float:
    """Edge of the stable set (``radius_at(x) < 1``) from ``inside`` towards the first unstable candidate (``+-inf``
    if none is): :data:`BISECTIONS` halvings of the bracket, or Brent's method on ``radius_at - 1`` (continuous) to
    :data:`EDGE_TOLERANCE` of it."""
    previous = inside
    for candidate in candidates:
        if not radius_at(candidate) < 1:
            if not bisect:
                return float(brentq(lambda x: radius_at(x) - 1, previous, candidate,
                                    xtol=EDGE_TOLERANCE * abs(candidate - previous)))
            lo, hi = previous, candidate
            for _ in range(BISECTIONS):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if radius_at(mid) < 1 else (lo, mid)
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
