"""The B-spline strip: frozen flow sampled at the actuator pitch and translated with B-splines (model ``strip``).

Each layer is an HCIPy :class:`~hcipy.InfiniteAtmosphericLayer` used as a *strip generator*: the layer is laid
along its wind direction at the sampling pitch and moved by exactly one pixel at a time, so every HCIPy step
extrudes one new, statistically consistent column (Assémat et al. 2006). Frames are then translations of
that long strip, interpolated in torch with B-splines (order 5 by default, the order HCIPy uses for
sub-pixel shifts). A frame costs a gather instead of an HCIPy evolve, and frame ``n`` depends only on the
seed and ``n``: any frame range can be generated, in any chunking, and gives the same numbers.

What it is good for: fast, any wind direction, and spatial statistics (structure function, variance) of the
screen sampled at the pitch. Its artefact: every actuator's time series is a piecewise polynomial with knots
every ``pitch / (v dt)`` frames, so temporal PSDs show comb peaks at multiples of ``v / pitch`` and collapse
above them, and a short linear filter extrapolates such a series almost exactly (the open-loop EOF floor in the
reference scenario: ``docs/findings.md``). Do not use it to judge prediction; use model ``exact``.
"""

from __future__ import annotations

import functools
import math

import hcipy
import numpy as np
import torch
from scipy.ndimage import spline_filter1d

#: HCIPy's achromatic screen is phase x wavelength, i.e. 2 pi x OPD in metres; this converts it to OPD in nm.
NM_PER_SCREEN_UNIT = 1e9 / (2 * np.pi)
#: Columns of the strip prefiltered together; prefilter blocks are fixed so results never depend on chunking.
_BLOCK_COLUMNS = 256
#: Extra columns each side of a block for the (IIR) spline prefilter; the quintic pole is 0.43, 0.43**48 ~ 1e-18.
_PREFILTER_MARGIN = 48


@functools.cache
def _bspline_polynomials(order: int) -> torch.Tensor:
    """``(order + 1, order + 1)`` matrix ``C`` with weights ``w_j(f) = sum_p f**p C[p, j]`` for ``f`` in [0, 1).

    For odd orders the knots of the centred B-spline are integers, so each weight is one polynomial in ``f``.
    """
    f = np.linspace(0.0, 1.0, order + 1, endpoint=False) + 0.5 / (order + 1)
    offsets = np.arange(order + 1) - (order - 1) // 2
    t = f[:, None] - offsets[None, :]
    half = (order + 1) / 2
    values = sum(
        (-1) ** k * math.comb(order + 1, k) * np.clip(t + half - k, 0, None) ** order for k in range(order + 2)
    ) / math.factorial(order)
    vandermonde = f[:, None] ** np.arange(order + 1)[None, :]
    return torch.as_tensor(np.linalg.solve(vandermonde, values))


def bspline_weights(frac: torch.Tensor, order: int) -> torch.Tensor:
    """Weights ``(..., order + 1)`` of the B-spline coefficients around a point at fractional offset ``frac``.

    The coefficients are those at nodes ``floor(x) - (order - 1) // 2 + j`` for ``j = 0..order``.
    """
    powers = frac.unsqueeze(-1) ** torch.arange(order + 1, dtype=frac.dtype)
    return powers @ _bspline_polynomials(order).to(frac.dtype)


class FrozenFlowStrip:
    """One realisation of one layer: a long strip along the wind, sampled at the actuator positions.

    Parameters
    ----------
    positions_m : ndarray
        ``(n_actuators, 2)`` actuator positions in metres.
    pitch_m : float
        Strip sampling pitch in metres.
    r0_m, r0_wavelength_m, outer_scale_m : float
        Layer turbulence strength (Fried parameter at a wavelength) and outer scale.
    wind_speed_mps, wind_direction_deg : float
        Wind of the layer: speed (m/s) and direction (degrees from +x towards +y).
    frame_period_s : float
        Time between frames in seconds.
    order : int
        B-spline interpolation order.
    seed : SeedSequence
        Seed of this realisation.
    """

    def __init__(
        self,
        positions_m: np.ndarray,
        pitch_m: float,
        r0_m: float,
        r0_wavelength_m: float,
        outer_scale_m: float,
        wind_speed_mps: float,
        wind_direction_deg: float,
        frame_period_s: float,
        order: int,
        seed: np.random.SeedSequence,
    ) -> None:
        self.order = order
        self.pitch_m = pitch_m
        self._seed = seed
        self._cn2 = hcipy.Cn_squared_from_fried_parameter(r0_m, r0_wavelength_m)
        self._outer_scale_m = outer_scale_m
        angle = math.radians(wind_direction_deg)
        u = positions_m[:, 0] * math.cos(angle) + positions_m[:, 1] * math.sin(angle)
        w = -positions_m[:, 0] * math.sin(angle) + positions_m[:, 1] * math.cos(angle)
        margin = order + 2
        # Across the wind: actuator w positions in strip rows; on nodes when the wind is along a grid axis.
        w_index = _snap((w - w.min()) / pitch_m) + margin
        self.n_rows = int(np.ceil(w_index.max())) + margin + 1
        # Along the wind: strip coordinate of actuator k at frame n is u_index[k] + n * columns_per_frame.
        self.u_index = torch.as_tensor(_snap((u.max() - u) / pitch_m) + margin + _PREFILTER_MARGIN)
        self._aligned = bool(torch.all(self.u_index == torch.round(self.u_index)))
        self.columns_per_frame = wind_speed_mps * frame_period_s / pitch_m
        self._w_weights = _interpolation_matrix(w_index, self.n_rows, order)  # (n_act, n_rows)
        self._n_initial_columns = max(self.n_rows, int(np.ceil(self.u_index.max().item())) + margin + 1)
        self._reset()

    def _reset(self) -> None:
        grid = hcipy.make_uniform_grid([self._n_initial_columns, self.n_rows],
                                       [self._n_initial_columns * self.pitch_m, self.n_rows * self.pitch_m])
        # One pixel per unit "time": every evolve extrudes exactly one new column, with no interpolation.
        self._layer = hcipy.InfiniteAtmosphericLayer(
            grid, self._cn2, self._outer_scale_m, velocity=self.pitch_m, use_interpolation=False,
            seed=np.random.default_rng(self._seed),
        )
        self._steps = 0
        screen = self._screen()
        self._raw = [screen[:, i] for i in range(screen.shape[1])]  # columns, prefiltered across the wind
        self._raw_offset = 0  # strip index of self._raw[0]
        self._blocks: dict[int, torch.Tensor] = {}

    def _screen(self) -> np.ndarray:
        opd_nm = np.asarray(self._layer.phase_for(1.0)).reshape(self.n_rows, self._n_initial_columns) * NM_PER_SCREEN_UNIT
        if self.order > 1:
            opd_nm = spline_filter1d(opd_nm, self.order, axis=0, mode="mirror")
        return opd_nm

    def _ensure_columns(self, stop: int) -> None:
        while self._raw_offset + len(self._raw) < stop:
            self._steps += 1
            self._layer.evolve_until(self._steps)
            column = np.asarray(self._layer.phase_for(1.0)).reshape(self.n_rows, -1)[:, -1] * NM_PER_SCREEN_UNIT
            if self.order > 1:
                column = spline_filter1d(column, self.order, mode="mirror")
            self._raw.append(column)

    def _forget_before(self, block: int) -> None:
        """Streaming: drop strip blocks and raw columns that frames from ``block`` on never read again."""
        for b in [b for b in self._blocks if b < block]:
            del self._blocks[b]
        first_needed = max(block * _BLOCK_COLUMNS - _PREFILTER_MARGIN, 0)
        drop = min(first_needed - self._raw_offset, len(self._raw))
        if drop > 0:
            del self._raw[:drop]
            self._raw_offset += drop

    def _block(self, b: int) -> torch.Tensor:
        """``(n_actuators, _BLOCK_COLUMNS)`` strip coefficients of block ``b``, contracted across the wind."""
        if b not in self._blocks:
            start, stop = b * _BLOCK_COLUMNS, (b + 1) * _BLOCK_COLUMNS
            lo, hi = max(start - _PREFILTER_MARGIN, 0), stop + _PREFILTER_MARGIN
            if lo < self._raw_offset:
                self._reset()
            self._ensure_columns(hi)
            raw = np.stack(self._raw[lo - self._raw_offset: hi - self._raw_offset], axis=1)
            if self.order > 1:
                raw = spline_filter1d(raw, self.order, axis=1, mode="mirror")
            coeffs = torch.as_tensor(raw[:, start - lo: stop - lo])
            self._blocks[b] = self._w_weights @ coeffs
        return self._blocks[b]

    def frames(self, start: int, stop: int, basis: torch.Tensor | None = None) -> torch.Tensor:
        """OPD (nm) of frames ``start..stop-1`` at the actuators, as a ``(frames, n_actuators)`` tensor.

        With an orthonormal ``(n_actuators, m)`` ``basis``, those modes are projected out of every frame.
        """
        half = (self.order - 1) // 2
        taps = torch.arange(self.order + 1)
        shift = torch.arange(start, stop, dtype=torch.float64) * self.columns_per_frame  # (T,) strip columns moved
        if self._aligned:
            # Every actuator sits on a strip node, so all share the fractional position of a frame: the first
            # coefficient of actuator k at frame n is u_index[k] + floor(shift[n]) - half.
            whole = torch.floor(shift)
            weights = bspline_weights(shift - whole, self.order)  # (T, order+1)
            u_index = self.u_index.long()
            lo = int(u_index.min() + whole[0]) - half
            hi = int(u_index.max() + whole[-1]) - half + self.order
        else:
            position = self.u_index.unsqueeze(0) + shift.unsqueeze(1)  # (T, K)
            base = torch.floor(position)
            weights = bspline_weights(position - base, self.order)  # (T, K, order+1)
            first = base.long() - half
            lo, hi = int(first.min()), int(first.max()) + self.order
        lo_block, hi_block = lo // _BLOCK_COLUMNS, hi // _BLOCK_COLUMNS
        self._forget_before(lo_block)
        coeffs = torch.cat([self._block(b) for b in range(lo_block, hi_block + 1)], dim=1)
        offset = lo_block * _BLOCK_COLUMNS
        if self._aligned:
            # Shift each actuator's row once so that a frame reads the same columns for every actuator; each frame
            # is then a weighted sum of order + 1 of those columns.
            c = (whole - whole[0]).long()
            width = int(c[-1]) + self.order + 1
            rows = (u_index + int(whole[0]) - half - offset).unsqueeze(1) + torch.arange(width)
            shifted = torch.gather(coeffs, 1, rows)  # (K, width)
            if basis is not None:  # projecting the few columns is cheaper than projecting every frame
                shifted = shifted - basis @ (basis.T @ shifted)
            columns = shifted.T.contiguous()  # (width, K)
            change = torch.nonzero(c[1:] != c[:-1]).flatten() + 1
            edges = [0, *change.tolist(), len(c)]
            if len(c) >= 4 * (len(edges) - 1):
                # Slow wind: long runs of frames share their columns; one small dense product per run.
                return torch.cat([weights[a:b] @ columns[int(c[a]): int(c[a]) + self.order + 1]
                                  for a, b in zip(edges[:-1], edges[1:], strict=True)])
            # Fast wind: a banded sparse matrix (order + 1 weights per frame) times the columns.
            t = len(c)
            index = torch.stack([torch.arange(t).repeat_interleave(self.order + 1), (c.unsqueeze(1) + taps).flatten()])
            banded = torch.sparse_coo_tensor(index, weights.flatten(), (t, width), check_invariants=False,
                                             is_coalesced=True)
            return torch.sparse.mm(banded, columns)
        index = (first - offset).T.unsqueeze(-1) + taps  # (K, T, order+1)
        values = torch.gather(coeffs, 1, index.reshape(coeffs.shape[0], -1)).view(index.shape)
        out = torch.einsum("ktj,tkj->tk", values, weights)
        return out if basis is None else out - (out @ basis) @ basis.T


def _snap(x: np.ndarray) -> np.ndarray:
    """Round values within 1e-9 of an integer, so grid-aligned positions sit exactly on strip nodes."""
    r = np.round(x)
    return np.where(np.abs(x - r) < 1e-9, r, x)


def _interpolation_matrix(index: np.ndarray, size: int, order: int) -> torch.Tensor:
    """``(len(index), size)`` B-spline interpolation weights at fractional positions ``index``."""
    idx = torch.as_tensor(index, dtype=torch.float64)
    base = torch.floor(idx)
    weights = bspline_weights(idx - base, order)
    cols = base.long().unsqueeze(-1) - (order - 1) // 2 + torch.arange(order + 1)
    out = torch.zeros(len(index), size, dtype=torch.float64)
    out.scatter_add_(1, cols, weights)
    return out
