"""Batched polynomial algebra in the delay operator ``z^-1`` for loop analysis (float64 torch).

A polynomial ``p(z) = p[0] + p[1] z^-1 + ... + p[L] z^-L`` is a tensor ``(..., L + 1)`` of its coefficients, one
row per actuator. A loop whose characteristic polynomial has ``p[0] = 1`` is stable when every root of
``z^L p(z)`` lies strictly inside the unit circle. :func:`add`, :func:`multiply`, :func:`evaluate` and
:func:`max_root_modulus` also take complex coefficients (one spatial Fourier mode of a loop).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

DTYPE = torch.float64


def pad(p: torch.Tensor, length: int) -> torch.Tensor:
    """``p`` with zero coefficients appended up to ``length``."""
    return torch.nn.functional.pad(p, (0, length - p.shape[-1])) if p.shape[-1] < length else p


def add(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a + b`` for polynomials of any lengths (batch dimensions broadcast)."""
    n = max(a.shape[-1], b.shape[-1])
    return pad(a, n) + pad(b, n)


def multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a * b`` (a convolution of coefficients; batch dimensions broadcast)."""
    if a.shape[-1] < b.shape[-1]:
        a, b = b, a
    shape = torch.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    dtype = torch.promote_types(torch.promote_types(a.dtype, b.dtype), DTYPE)
    out = torch.zeros(*shape, a.shape[-1] + b.shape[-1] - 1, dtype=dtype, device=a.device)
    for j in range(b.shape[-1]):  # the short factor: a few terms
        out[..., j: j + a.shape[-1]] += a * b[..., j: j + 1]
    return out


def delay(frames: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """``z^-frames``."""
    out = torch.zeros(frames + 1, dtype=DTYPE, device=device)
    out[frames] = 1.0
    return out


def fractional_delay(delay_frames: float, device: torch.device | str = "cpu") -> torch.Tensor:
    """The DM's response to a command after ``delay_frames = d + f`` frames: ``z^-d ((1 - f) + f z^-1)``.

    The command acting during a frame is the time average of the commands over it: a fraction ``f`` of the frame
    still sees the previous command. ``f = 0`` is the pure delay ``z^-d``.
    """
    d = math.floor(delay_frames)
    f = delay_frames - d
    out = torch.zeros(d + 2, dtype=DTYPE, device=device)
    out[d], out[d + 1] = 1.0 - f, f
    return out


def evaluate(p: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """``p(e^{i omega})``: ``(..., L + 1)`` coefficients at frequencies ``(F,)`` rad/frame -> ``(..., F)`` complex."""
    k = torch.arange(p.shape[-1], dtype=DTYPE, device=p.device)
    phasor = torch.exp(-1j * omega.to(DTYPE).unsqueeze(-1) * k)  # (F, L + 1)
    return p.to(phasor.dtype) @ phasor.T


def max_root_modulus(p: torch.Tensor) -> torch.Tensor:
    """Largest root modulus of monic ``p`` (``p[..., 0] = 1``), from the eigenvalues of its companion matrix."""
    p = trim(p)
    n = p.shape[-1] - 1
    if n == 0:
        return torch.zeros(p.shape[:-1], dtype=DTYPE, device=p.device)
    companion = torch.zeros(*p.shape[:-1], n, n, dtype=p.dtype, device=p.device)
    companion[..., 0, :] = -p[..., 1:] / p[..., :1]
    if n > 1:
        companion[..., 1:, :-1] = torch.eye(n - 1, dtype=DTYPE, device=p.device)
    return torch.linalg.eigvals(companion).abs().amax(-1)


def trim(p: torch.Tensor) -> torch.Tensor:
    """``p`` without trailing coefficients that are zero in every row (they only add roots at ``z = 0``)."""
    nonzero = (p != 0).reshape(-1, p.shape[-1]).any(0).nonzero()
    return p[..., : int(nonzero[-1]) + 1] if len(nonzero) else p[..., :1]


def real_crossings(a: torch.Tensor, b: torch.Tensor, n_grid: int = 1024,
                   chunk_rows: int = 1024) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Real parameters ``t`` at which ``a(z) + t b(z)`` has a root on the unit circle, per row.

    A root ``e^{i w}`` for real ``t`` needs ``a / b`` real there, so the crossings are the zeros of
    ``h(w) = Im(a(e^{iw}) conj(b(e^{iw})))`` on ``[0, pi]`` (real coefficients: ``-w`` mirrors ``w``), with
    ``t = -a / b``. ``w = 0`` and ``pi`` always qualify; interior zeros are bracketed by sign changes of ``h`` on a
    grid of ``n_grid`` frequencies and refined to machine precision (Illinois false position). Zeros that touch
    without a sign change (tangencies) or two zeros within one grid step are missed.

    Parameters
    ----------
    a, b : Tensor
        ``(rows, L + 1)`` real coefficients.

    Returns
    -------
    rows, t, omega : Tensor
        One entry per crossing: its row, its parameter and its frequency in rad/frame.
    """
    n = max(a.shape[-1], b.shape[-1])
    a, b = pad(a, n), pad(b, n)
    out_rows, out_t, out_w = [], [], []
    for start in range(0, a.shape[0], chunk_rows):
        ac, bc = a[start: start + chunk_rows], b[start: start + chunk_rows]
        spectrum_a = torch.fft.rfft(ac, n=2 * n_grid)  # a(e^{i w_j}), w_j = pi j / n_grid
        spectrum_b = torch.fft.rfft(bc, n=2 * n_grid)
        h = (spectrum_a * spectrum_b.conj()).imag[:, 1:-1]  # interior: h vanishes at 0 and pi by symmetry
        change = (h[:, 1:] >= 0) != (h[:, :-1] >= 0)
        rows, cell = change.nonzero(as_tuple=True)
        lo = (cell + 1).to(DTYPE) * math.pi / n_grid
        hi = lo + math.pi / n_grid
        omega_root = _refine(ac[rows], bc[rows], lo, hi, h[rows, cell], h[rows, cell + 1])
        omega = torch.cat([omega_root, torch.zeros(len(ac), dtype=DTYPE),
                           torch.full((len(ac),), math.pi, dtype=DTYPE)])
        rows = torch.cat([rows, torch.arange(len(ac)), torch.arange(len(ac))])
        value_a = _at(ac[rows], omega)
        value_b = _at(bc[rows], omega)
        power = value_b.abs().pow(2)
        t = -(value_a * value_b.conj()).real / power.clamp(min=torch.finfo(DTYPE).tiny)
        # A genuine crossing solves a + t b = 0 (not a zero of b, where t would be infinite).
        ok = (power > 0) & ((value_a + t * value_b).abs() <= 1e-8 * (value_a.abs() + (t * value_b).abs() + 1e-300))
        out_rows.append(rows[ok] + start)
        out_t.append(t[ok])
        out_w.append(omega[ok])
    return torch.cat(out_rows), torch.cat(out_t), torch.cat(out_w)


def _at(p: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """``p[r](e^{i omega[r]})`` row by row (Horner's scheme in ``z^-1``)."""
    z_inv = torch.exp(-1j * omega)
    out = p[:, -1].to(z_inv.dtype)
    for k in range(p.shape[-1] - 2, -1, -1):
        out = out * z_inv + p[:, k]
    return out


def _im_product(a: torch.Tensor, b: torch.Tensor, omega: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``Im(a conj b)`` and ``|a| |b|`` at ``e^{i omega}``, row by row."""
    product = _at(a, omega) * _at(b, omega).conj()
    return product.imag, product.abs()


def _refine(a: torch.Tensor, b: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, h_lo: torch.Tensor,
            h_hi: torch.Tensor, iterations: int = 60) -> torch.Tensor:
    """Zeros of ``Im(a conj b)`` in brackets ``[lo, hi]`` (:func:`illinois_zeros`)."""
    return illinois_zeros(lambda mid, open_: _im_product(a[open_], b[open_], mid), lo, hi, h_lo, h_hi, iterations)


#: ``evaluate(mid, open)``: the function and its scale (``|a| |b|``) at ``mid`` for the brackets ``open``.
BracketFunction = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def illinois_zeros(evaluate: BracketFunction, lo: torch.Tensor, hi: torch.Tensor, h_lo: torch.Tensor,
                   h_hi: torch.Tensor, iterations: int = 60) -> torch.Tensor:
    """Zeros of a function in brackets ``[lo, hi]`` (values ``h_lo``, ``h_hi`` of opposite signs) by false position
    with the Illinois modification; ``evaluate(mid, open)`` gives the function at ``mid`` for the brackets still open.

    Each bracket stops once it has converged (a bracket below 1e-13 rad, or the function at rounding level of its
    scale); later iterations work on the brackets still open only, so a few slow ones cost little (thousands of
    actuators have tens of thousands of brackets)."""
    lo, hi, h_lo, h_hi = lo.clone(), hi.clone(), h_lo.clone(), h_hi.clone()
    side = torch.zeros_like(lo)  # -1: lo moved last time, +1: hi moved
    open_ = torch.arange(len(lo))
    for _ in range(iterations):
        if not len(open_):
            break
        left, right, hl, hh, sd = lo[open_], hi[open_], h_lo[open_], h_hi[open_], side[open_]
        mid = (left * hh - right * hl) / (hh - hl)
        mid = torch.where((mid > left) & (mid < right), mid, 0.5 * (left + right))
        h_mid, scale = evaluate(mid, open_)
        move_lo = (h_mid >= 0) == (hl >= 0)
        # Illinois: an end kept twice in a row has its value halved, so that both ends converge.
        hh = torch.where(move_lo, torch.where(sd < 0, 0.5 * hh, hh), h_mid)
        hl = torch.where(move_lo, h_mid, torch.where(sd > 0, 0.5 * hl, hl))
        left, right = torch.where(move_lo, mid, left), torch.where(move_lo, right, mid)
        lo[open_], hi[open_], h_lo[open_], h_hi[open_] = left, right, hl, hh
        side[open_] = torch.where(move_lo, -1.0, 1.0).to(lo.dtype)
        still = ~((right - left <= 1e-13) | (h_mid.abs() <= 1e-14 * scale))
        open_ = open_[still]
    return torch.where(h_lo.abs() < h_hi.abs(), lo, hi)


def nearest_around(rows: torch.Tensor, values: torch.Tensor, centre: torch.Tensor,
                   n_rows: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per row, the largest value ``<= centre`` and the smallest ``> centre`` (``-inf`` / ``inf`` when none)."""
    below = torch.where(values <= centre[rows], values, -math.inf)
    above = torch.where(values > centre[rows], values, math.inf)
    lower = torch.full((n_rows,), -math.inf, dtype=DTYPE).scatter_reduce(0, rows, below, "amax")
    upper = torch.full((n_rows,), math.inf, dtype=DTYPE).scatter_reduce(0, rows, above, "amin")
    return lower, upper
