"""Stability of a linear controller given per group by its frequency response, not its polynomial coefficients: the
margins and transfer functions of :func:`eofnn.analysis.stability.analyse_polynomials`, from the same
characteristic equation ``P = D - g Q N`` evaluated on the unit circle.

For predictive Fourier control (:class:`~eofnn.control.fourier.FourierPredictor`): each spatial Fourier mode's
filter has up to 18 states whose poles cluster near the unit circle at nearly one angle, and the coefficients of its
polynomials then hold the loop only to rounding near that angle (most sign changes of ``Im(D conj(N))`` per mode are
rounding, and their roots put stable modes outside the circle: ``docs/findings.md``). Its
response by partial fractions (``response(omega, rows)``: ``D / Delta`` and ``N / Delta`` with a common factor
``Delta`` that has no zero on the circle, so no ratio changes) and its poles from its state space (``moduli(setup)``)
are exact to rounding. The modes' coefficients are complex, so crossings are searched on the whole circle (no
mirror) and their frequencies folded into ``[0, pi]`` (a mode and its conjugate make one real oscillation).

- DM gain: ``P = a + g b`` (``a = D``, ``b = -Q N``) has a root ``e^{i w}`` where ``Im(a conj b) = 0``, at ``g =
  -a / b``: sign changes on a grid, refined by Illinois false position, and the grid points where it vanishes (0 and
  pi for real coefficients); the interval is the one around the plant's gain.
- Delay: between ``m`` and ``m + 1`` frames ``P = (D - g w z^-m N) + f (-g w z^-m (z^-1 - 1) N)``, the first
  ``m + f`` beyond the plant's delay; whole extra frames from the poles at ``tau + j``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace

import torch

from eofnn.analysis.polynomials import illinois_zeros, nearest_around
from eofnn.analysis.stability import LoopSetup, StabilityResult
from eofnn.resources import require_memory

DTYPE = torch.float64
#: ``response(omega, rows)``: ``(a, b)`` or ``(D, N)`` values ``(R, F)`` at ``omega`` ``(R or 1, F)`` for groups ``rows``.
Response = Callable[[torch.Tensor, torch.Tensor | None], tuple[torch.Tensor, torch.Tensor]]


def _refine(pair: Response, rows: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, h_lo: torch.Tensor,
            h_hi: torch.Tensor, iterations: int = 60) -> torch.Tensor:
    """Zeros of ``Im(a conj b)`` of ``pair`` in brackets ``[lo, hi]`` (one per entry of ``rows``), by false position
    with the Illinois modification (:func:`~eofnn.analysis.polynomials.illinois_zeros`)."""
    def evaluate(mid: torch.Tensor, open_: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        a, b = pair(mid.unsqueeze(1), rows[open_])
        product = (a * b.conj()).squeeze(1)
        return product.imag, product.abs()

    return illinois_zeros(evaluate, lo, hi, h_lo, h_hi, iterations)


def crossings(pair: Response, grid_values: tuple[torch.Tensor, torch.Tensor],
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(rows, t, omega)``: the real ``t`` at which ``a + t b`` (``pair``'s, per group) vanishes on the unit
    circle, with their groups and frequencies (rad/frame, folded into ``[0, pi]``). ``grid_values``: ``(a, b)``
    ``(groups, F)`` on :func:`circle` (``F`` frequencies around it), where sign changes bracket them."""
    grid = circle(grid_values[0].shape[1])
    product = grid_values[0] * grid_values[1].conj()
    h = product.imag
    found, cell = ((h[:, 1:] >= 0) != (h[:, :-1] >= 0)).nonzero(as_tuple=True)
    omega = _refine(pair, found, grid[cell], grid[cell + 1], h[found, cell], h[found, cell + 1])
    # Grid points where h vanishes to rounding are crossings too: w = 0 and pi of a loop with real coefficients
    # (the mode of frequency 0), where h touches zero without changing sign.
    exact, point = (h.abs() <= 1e-12 * product.abs()).nonzero(as_tuple=True)
    found, omega = torch.cat([found, exact]), torch.cat([omega, grid[point]])
    a, b = pair(omega.unsqueeze(1), found)
    a, b = a.squeeze(1), b.squeeze(1)
    power = b.abs().pow(2)
    t = -(a * b.conj()).real / power.clamp(min=torch.finfo(DTYPE).tiny)
    ok = (power > 0) & ((a + t * b).abs() <= 1e-8 * (a.abs() + (t * b).abs() + 1e-300))
    folded = torch.remainder(omega, 2 * math.pi)
    return found[ok], t[ok], torch.minimum(folded, 2 * math.pi - folded)[ok]


def circle(points: int) -> torch.Tensor:
    """``points`` frequencies from 0 to ``2 pi`` included (rad/frame): ``2 pi j / (points - 1)``."""
    return torch.arange(points, dtype=DTYPE) * (2 * math.pi / (points - 1))


def _plant(setup: LoopSetup, omega: torch.Tensor, delay_frames: float | None = None) -> torch.Tensor:
    """``z^-d ((1 - f) + f z^-1)`` at ``omega`` for the plant's delay (or ``delay_frames``)."""
    tau = setup.delay_frames if delay_frames is None else delay_frames
    d = math.floor(tau)
    z_inv = torch.exp(-1j * omega)
    return z_inv**d * ((1 - (tau - d)) + (tau - d) * z_inv)


def analyse_response(response: Response, moduli: Callable[[LoopSetup], torch.Tensor], groups: int,
                     setup: LoopSetup, frequencies_hz: torch.Tensor, *, kind: str, structure: str,
                     history_length: int, n_grid: int = 1024) -> StabilityResult:
    """The :class:`StabilityResult` of a controller whose ``groups`` loops are ``response(omega, rows) -> (D, N)``
    (up to a common factor without zeros on the circle) with closed-loop pole moduli ``moduli(setup)``; crossings
    are bracketed on ``2 n_grid`` frequencies around the circle (those of ``analyse_polynomials`` on each half)."""
    start = time.perf_counter()
    g, gw = setup.dm_gain, setup.dm_gain * setup.wfs_gain
    modulus = moduli(setup)
    stable = modulus < 1

    def gain_pair(omega: torch.Tensor, rows: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        d, n = response(omega, rows)
        return d, -setup.wfs_gain * _plant(setup, omega) * n

    grid = circle(2 * n_grid + 1)
    require_memory(2 * 16 * groups * len(grid), f"the frequency responses of {groups} modes on {len(grid)} frequencies")
    on_grid = [response(grid.unsqueeze(0), torch.arange(i, min(i + 128, groups))) for i in range(0, groups, 128)]
    d_grid, n_grid_values = torch.cat([d for d, _ in on_grid]), torch.cat([n for _, n in on_grid])
    rows, gains, omega = crossings(gain_pair, (d_grid, -setup.wfs_gain * _plant(setup, grid) * n_grid_values))
    lower, upper = nearest_around(rows, gains, torch.full((groups,), g, dtype=DTYPE), groups)
    interval = torch.stack([lower, upper], 1)
    interval[~stable] = math.nan
    crossing_hz = torch.full((groups, 2), math.nan, dtype=DTYPE)
    hz = omega * setup.frame_rate_hz / (2 * math.pi)
    for column, bound in enumerate((lower, upper)):
        hit = gains == bound[rows]
        crossing_hz[:, column].scatter_reduce_(0, rows[hit], hz[hit], "amin", include_self=False)
    tau = float(setup.delay_frames)
    delay_margin = torch.full((groups,), math.inf, dtype=DTYPE)
    for m in range(math.floor(tau), math.floor(tau) + setup.max_extra_delay_frames + 1):
        left = torch.isinf(delay_margin).nonzero().squeeze(-1)
        if not len(left):
            break

        def delay_pair(omega: torch.Tensor, rows: torch.Tensor | None, m: int = m, left: torch.Tensor = left):
            d, n = response(omega, left if rows is None else left[rows])
            z_inv = torch.exp(-1j * omega)
            return d - gw * z_inv**m * n, -gw * z_inv**m * (z_inv - 1) * n

        z_m = torch.exp(-1j * grid) ** m
        found, fraction, _ = crossings(delay_pair, (d_grid[left] - gw * z_m * n_grid_values[left],
                                                    -gw * z_m * (torch.exp(-1j * grid) - 1) * n_grid_values[left]))
        critical = m + fraction
        ok = (fraction >= 0) & (fraction <= 1) & (critical > tau)
        delay_margin[left] = torch.full((len(left),), math.inf, dtype=DTYPE).scatter_reduce(
            0, found[ok], critical[ok] - tau, "amin")
    integer = torch.full((groups,), setup.max_extra_delay_frames, dtype=torch.int64)
    for j in range(1, setup.max_extra_delay_frames + 1):
        left = (integer == setup.max_extra_delay_frames).nonzero().squeeze(-1)
        if not len(left):
            break
        later = replace(setup, delay_frames=tau + j, controller_delay_frames=setup.controller_delay)
        integer[left[moduli(later)[left] >= 1]] = j - 1
    delay_margin[~stable], integer[~stable] = math.nan, -1
    omega_grid = (2 * math.pi * frequencies_hz / setup.frame_rate_hz).to(DTYPE).unsqueeze(0)
    rejection, noise = [], []
    for first in range(0, groups, 256):
        d, n = response(omega_grid, torch.arange(first, min(first + 256, groups)))
        loop = _plant(setup, omega_grid) * n
        rejection.append(d / (d - gw * loop))
        noise.append(g * loop / (d - gw * loop))
    result = StabilityResult(kind, structure, history_length, setup, modulus, interval, crossing_hz, delay_margin,
                             integer, frequencies_hz, torch.cat(rejection), torch.cat(noise))
    result.analysis_seconds = time.perf_counter() - start
    return result
