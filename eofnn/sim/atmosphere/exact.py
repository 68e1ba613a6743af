"""Exact frozen flow: a von Kármán screen synthesised in the Fourier domain, evaluated where each actuator looks.

One layer is a Fourier series in its own frame (``u`` along the wind, ``w`` across), periodic over ``P`` along the
wind and over ``N_w`` line spacings across it. Frame ``n`` at actuator ``k`` is that series at
``(u_k - n v dt, w_k)``: no frame is ever interpolated from another, so frozen flow holds to rounding and a frame
depends only on the seed and ``n``.

*Across the wind*: for a wind along a lattice direction of the grid (``atan2(p, q)`` with small integers: 0, 90,
180, 270 and 45 degrees, atan(1/2), ...) the actuators lie on lines parallel to it, ``pitch / hypot(p, q)`` apart.
A field read only on those lines cannot tell an across-wind frequency ``f_w`` from ``f_w + a / spacing``, so each
lattice frequency carries the variance of all its aliases (summed over ``|a| <= _ALIASES``): the lines then have
the cross-covariance of the continuous screen, periodised over ``N_w`` spacings (Poisson summation) — exact once
``N_w`` spacings hold several outer scales, where the von Kármán covariance has decayed as ``exp(-2 pi r / L0)``.
Other directions put every actuator on a line of its own: :mod:`eofnn.sim.atmosphere.anywind` handles them.

*Along the wind* the field on each line is a trigonometric polynomial (frequencies up to ``f_max``: twice the
frame rate's Nyquist ``1 / (2 v dt)`` and at least ``_SPATIAL_BAND / pitch``). It is evaluated at every
actuator's exact, non-grid position with a type-2 non-uniform FFT ("exponential of semicircle" kernel, as FINUFFT):
the line's coefficients, divided by the kernel's Fourier transform, are transformed to a grid ``_OVERSAMPLING``
times finer than the band needs, and a value is the sum of ``2 * _SPREAD`` grid points weighted by the kernel —
exact to about 2e-12 of the RMS (``tests/test_exact_turbulence.py`` checks it against the direct Fourier sum).
The frame step is a whole number of fine-grid samples, so each actuator's weights are fixed and a frame is one
small matrix product.

*Sensing kernel*: ``subaperture`` multiplies the spectrum by ``sinc(d f_x) sinc(d f_y)`` (the mean over the
actuator's ``d x d`` subaperture, ``d`` = pitch, telescope-frame frequencies); ``point`` reads the field at the
actuator. The subaperture's transform has zeros: with the wind along x the temporal PSD has true nulls at
multiples of ``v / d`` (not peaks; the theory in the tests has them too).

Memory per layer and realisation: the fine series, ``8 * N_f * n_lines`` bytes with
``N_f ~ 2 _OVERSAMPLING f_max (screen_frames v dt + D)`` samples and ``n_lines = n_across (|p| + |q|)``: at 1 kHz,
5.1 m/s along x and 40 across about ``32 * (screen_frames + 1570) * 40`` bytes, 23 MB for 16384 frames and
131 MB for 1e5 frames; the set-up needs about as much again for a moment, and streaming keeps one block of
``_BLOCK_FRAMES`` frames (41 MB at 40 across). Set-up time grows with ``screen_frames`` (measured:
``docs/findings.md``).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from eofnn.errors import require
from eofnn.lazy import lazy_module
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.sensing.kernels import KERNELS, kernel_power

torch = lazy_module("torch")

#: Exact von Kármán coefficient (24/5 Γ(6/5))^(5/6) Γ(11/6)² / (2 π^(11/3)) of 0.023 r0^(-5/3) (f² + L0^-2)^(-11/6).
VON_KARMAN_COEFFICIENT = 0.022896
#: Along-wind band in units of the frame rate's Nyquist frequency 1 / (2 v dt) (aliasing of the frames included).
_TEMPORAL_BAND = 2.0
#: Smallest along-wind band in cycles per actuator pitch, for slow frame rates.
_SPATIAL_BAND = 16.0
#: Fine-grid oversampling of the non-uniform FFT, half-width (fine samples) and shape of its "exponential of
#: semicircle" kernel exp(beta (sqrt(1 - z²) - 1)) (Barnett et al. 2019): 12 taps give ~1e-11 of the RMS.
_OVERSAMPLING = 2
_SPREAD = 6
_KERNEL_BETA = 2.30 * 2 * _SPREAD
#: Across-wind aliases folded onto the lattice; beyond them the variance left out is < 1e-4 of the highest
#: lattice frequency's (the spectrum falls as a^(-11/3) for points, a^(-17/3) through a subaperture).
_ALIASES = {"subaperture": 3, "point": 8}
#: Periods (along and across the wind) in outer scales; the periodic images then add < 1e-7 of the covariance.
_PERIOD_OUTER_SCALES = 3.0
#: Frames computed together; fixed so that results never depend on how frames are asked for.
_BLOCK_FRAMES = 4096
#: Spectrum samples (frequencies x lattice x aliases) evaluated together: bounds the set-up's memory (8 MB).
_FREQUENCY_CHUNK_ELEMENTS = 2**20
#: Variance tables up to this size are kept and shared by the realisations of a layer (they need no seed).
_MAX_SHARED_VARIANCE_BYTES = 128 * 2**20
#: Refuse a screen whose fine series would exceed this many bytes per layer and realisation.
_MAX_SERIES_BYTES = 2 * 2**30
#: Wind directions (q, p) along which the actuators line up: atan2(p, q) with small coprime p, q.
_MAX_SLOPE = 4
_LATTICE_DIRECTIONS = [(q, p) for q in range(-_MAX_SLOPE, _MAX_SLOPE + 1) for p in range(-_MAX_SLOPE, _MAX_SLOPE + 1)
                       if math.gcd(p, q) == 1]
#: How close (degrees) a wind direction must be to a lattice direction; it is then taken as that direction.
_DIRECTION_TOLERANCE_DEG = 1e-6


def von_karman_psd(f_per_m: np.ndarray, r0_m: float, outer_scale_m: float) -> np.ndarray:
    """Von Kármán phase power spectral density in rad² m² at spatial frequency ``f_per_m`` (cycles/m)."""
    return VON_KARMAN_COEFFICIENT * r0_m ** (-5 / 3) * (f_per_m**2 + outer_scale_m**-2) ** (-11 / 6)


def spreading_kernel(distance: np.ndarray) -> np.ndarray:
    """The non-uniform FFT's kernel at ``distance`` fine samples (zero beyond ``_SPREAD``)."""
    z2 = np.clip(1 - (distance / _SPREAD) ** 2, 0, None)
    return np.where(np.abs(distance) <= _SPREAD, np.exp(_KERNEL_BETA * (np.sqrt(z2) - 1)), 0.0)


def spreading_kernel_transform(frequency: np.ndarray) -> np.ndarray:
    """Fourier transform of :func:`spreading_kernel` at ``frequency`` (cycles per fine sample), by quadrature."""
    z, w = np.polynomial.legendre.leggauss(4 * _SPREAD + 40)  # the kernel is smooth: exact to rounding
    phase = np.cos(2 * np.pi * np.multiply.outer(np.asarray(frequency, dtype=float), z * _SPREAD))
    return _SPREAD * phase @ (w * np.exp(_KERNEL_BETA * (np.sqrt(1 - z**2) - 1)))


def nice_fft_size(n: int) -> int:
    """Smallest even integer ``>= n`` with no prime factor above 5."""
    best = None
    p2 = 2
    while best is None or p2 < best:
        p3 = p2
        while best is None or p3 < best:
            p5 = p3
            while p5 < n:
                p5 *= 5
            best = p5 if best is None else min(best, p5)
            p3 *= 3
        p2 *= 2
    return best


def lattice_direction(direction_deg: float) -> tuple[int, int] | None:
    """``(p, q)``, coprime with ``|p|, |q| <= _MAX_SLOPE``, such that the wind blows along ``(q, p)`` on the grid.

    Such a wind keeps every actuator on a line parallel to it (lines ``pitch / hypot(p, q)`` apart): 0, 90, 180 and
    270 degrees, 45 degrees and its multiples, atan(1/2) = 26.565... degrees, and so on. ``None`` for any other
    direction (:mod:`eofnn.sim.atmosphere.anywind` evaluates those).
    """
    angle = math.radians(direction_deg)
    for q, p in sorted(_LATTICE_DIRECTIONS, key=lambda v: abs(v[0]) + abs(v[1])):
        error = math.remainder(angle - math.atan2(p, q), 2 * math.pi)
        if abs(error) < math.radians(_DIRECTION_TOLERANCE_DEG):
            return p, q
    return None


def wind_axes(grid: ActuatorGrid, direction_deg: float) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """``(u_m, line, line_spacing_m, unit)``: along-wind coordinate (m) and across-wind line index of each active
    actuator, the spacing of those lines (m) and the wind's unit vector (x, y).
    """
    direction = lattice_direction(direction_deg)
    require(direction is not None, f"wind_direction_deg={direction_deg!r} is not a lattice direction of the grid "
                                   "(atan2(p, q), |p|, |q| <= 4): the lines model cannot take it")
    p, q = direction
    norm = math.hypot(p, q)
    unit = np.array([q, p]) / norm
    x, y = grid.positions_m.T
    rows, cols = grid.indices.T
    across = rows * q - cols * p  # (-x p + y q) / pitch up to a constant: an integer per line
    return x * unit[0] + y * unit[1], across - across.min(), grid.pitch_m / norm, unit


def lattice_variance_nm2(r0_m: float, r0_wavelength_m: float, outer_scale_m: float, kernel: str, pitch_m: float,
                         line_spacing_m: float, unit: tuple[float, float], n_aliases: int, period_m: float,
                         n_lattice: int, q_first: int, q_stop: int) -> np.ndarray:
    """``(q_stop - q_first, n_lattice)`` variance (nm²) of the Fourier coefficients ``(q, l)``, ``q`` in a range.

    Along-wind frequency ``q / period_m``, across-wind lattice frequency ``fftfreq(n_lattice, line_spacing_m)[l]``
    plus its aliases ``a / line_spacing_m`` (``|a| <= n_aliases``): the spectrum times the kernel's squared
    transform (the subaperture's ``sinc(pitch f_x) sinc(pitch f_y)`` in the telescope frame, the wind along
    ``unit``), over one frequency cell.
    Single precision: the weights of a random field need no more.
    """
    d, e_x, e_y = line_spacing_m, np.float32(unit[0]), np.float32(unit[1])
    f_w = np.fft.fftfreq(n_lattice, d)[:, None] + np.arange(-n_aliases, n_aliases + 1)[None, :] / d
    f_w2 = (f_w**2 + outer_scale_m**-2).astype(np.float32)
    f_w = f_w.astype(np.float32)
    cell = (r0_wavelength_m / (2 * np.pi) * 1e9) ** 2 / (period_m * n_lattice * d)  # rad² per cell -> nm²
    out = np.empty((q_stop - q_first, n_lattice), dtype=np.float32)
    chunk = max(1, _FREQUENCY_CHUNK_ELEMENTS // f_w.size)
    for first in range(q_first, q_stop, chunk):
        f_u = (np.arange(first, min(first + chunk, q_stop)) / period_m).astype(np.float32)[:, None, None]
        psd = (f_u**2 + f_w2[None]) ** np.float32(-11 / 6)
        power = kernel_power(kernel, pitch_m, f_u, f_w, e_x, e_y)
        if power is not None:
            psd *= power
        out[first - q_first: first - q_first + len(f_u)] = psd.sum(-1) * np.float32(
            VON_KARMAN_COEFFICIENT * r0_m ** (-5 / 3) * cell)
    return out


@functools.lru_cache(maxsize=4)
def _shared_variance_nm2(*key) -> np.ndarray:
    """The whole variance table of a small screen, shared by realisations (it does not depend on the seed)."""
    out = lattice_variance_nm2(*key)
    out.flags.writeable = False
    return out


class ExactFrozenFlow:
    """One realisation of one layer moving along a lattice direction, seen through a sensing kernel, on the actuators.

    Parameters
    ----------
    grid : ActuatorGrid
        Actuators (positions, lines and pitch).
    r0_m, r0_wavelength_m, outer_scale_m : float
        Layer's Fried parameter (m) at a wavelength (m), and the outer scale (m, finite).
    wind_speed_mps, wind_direction_deg : float
        Wind speed (m/s, > 0) and direction (degrees from +x towards +y, along a lattice direction: see
        :func:`lattice_direction`; :class:`eofnn.sim.atmosphere.anywind.AnyWindFrozenFlow` takes any other).
    frame_period_s : float
        Time between frames in seconds.
    kernel : {"subaperture", "point"}
        Sensing kernel.
    screen_frames : int
        Frames the screen holds: frames ``0 .. screen_frames - 1`` can be asked for, in any order.
    seed : SeedSequence
        Seed of this realisation.
    """

    def __init__(self, grid: ActuatorGrid, r0_m: float, r0_wavelength_m: float, outer_scale_m: float,
                 wind_speed_mps: float, wind_direction_deg: float, frame_period_s: float, kernel: str,
                 screen_frames: int, seed: np.random.SeedSequence) -> None:
        require(wind_speed_mps > 0, f"wind_speed_mps={wind_speed_mps!r} is invalid for model 'exact': it must be > 0")
        require(math.isfinite(outer_scale_m),
                f"outer_scale_m={outer_scale_m!r} is invalid for model 'exact': it must be finite (metres)")
        require(kernel in KERNELS, f"kernel={kernel!r} is invalid: allowed are {', '.join(KERNELS)}")
        self.screen_frames = screen_frames
        self._rng = np.random.default_rng(seed)
        self._plan(grid, outer_scale_m, wind_speed_mps * frame_period_s, wind_direction_deg)
        self._series = self._synthesise(r0_m, r0_wavelength_m, outer_scale_m, kernel)
        self._block_frames = min(_BLOCK_FRAMES, screen_frames)
        self._buffer: torch.Tensor | None = None
        self._block_index = -1

    def _plan(self, grid: ActuatorGrid, outer_scale_m: float, step_m: float, direction_deg: float) -> None:
        """Sizes: fine grid along the wind, lattice across it, and each actuator's kernel weights."""
        self.pitch_m = grid.pitch_m
        u, line, self.line_spacing_m, self._unit = wind_axes(grid, direction_deg)
        f_max = max(_TEMPORAL_BAND / (2 * step_m), _SPATIAL_BAND / grid.pitch_m)
        self.fine_per_frame = math.ceil(2 * _OVERSAMPLING * f_max * step_m - 1e-9)  # integer fine samples per frame
        self.fine_m = step_m / self.fine_per_frame
        # Position (fine samples) at frame n: n * fine_per_frame + offset; the most downwind actuator starts first.
        offset = (u.max() - u) / self.fine_m + _SPREAD
        offset = np.where(np.abs(offset - np.round(offset)) < 1e-9, np.round(offset), offset)  # on-grid stays on
        needed = int(np.ceil(offset.max())) + self.fine_per_frame * self.screen_frames + _SPREAD + 2
        self.n_fine = nice_fft_size(max(needed, math.ceil(_PERIOD_OUTER_SCALES * outer_scale_m / self.fine_m)))
        self.n_modes = self.n_fine // (2 * _OVERSAMPLING)  # along-wind frequencies q in [-n_modes, n_modes]
        self.n_lines = int(line.max()) + 1
        self.n_lattice = nice_fft_size(max(2 * self.n_lines, math.ceil(_PERIOD_OUTER_SCALES * outer_scale_m
                                                                       / self.line_spacing_m)))
        require(8 * self.n_fine * self.n_lines <= _MAX_SERIES_BYTES,
                f"the exact screen needs {8 * self.n_fine * self.n_lines / 2**30:.1f} GiB per layer "
                f"(screen_frames={self.screen_frames}, {step_m * 1e3:.3g} mm per frame): lower screen_frames")
        base = np.floor(offset).astype(np.int64) - _SPREAD + 1
        weights = spreading_kernel(offset[:, None] - (base[:, None] + np.arange(2 * _SPREAD)))
        # Every actuator of a line reads windows of _WINDOW fine samples starting on multiples of fine_per_frame;
        # its 2 * _SPREAD weights sit at its residue inside the window, so a line is one matrix product per block.
        residue = base % self.fine_per_frame
        self._window = 2 * _SPREAD + self.fine_per_frame - 1
        padded = np.zeros((len(u), self._window))
        for r in np.unique(residue):
            padded[residue == r, r: r + 2 * _SPREAD] = weights[residue == r]
        self._lines = []
        for j in np.unique(line):
            members = np.flatnonzero(line == j)
            contiguous = bool(np.all(np.diff(members) == 1))  # rows of the grid: written as one slice
            self._lines.append((int(j), slice(members[0], members[-1] + 1) if contiguous else torch.as_tensor(members),
                                torch.as_tensor((base[members] - residue[members]) // self.fine_per_frame),
                                torch.as_tensor(padded[members])))
        self.n_actuators = len(u)

    def _synthesise(self, r0_m: float, r0_wavelength_m: float, outer_scale_m: float, kernel: str) -> torch.Tensor:
        """``(n_lines, n_fine)`` fine series: OPD (nm) of each line, deconvolved by the kernel's transform."""
        n_aliases = _ALIASES[kernel]
        if kernel == "subaperture" and 0 not in self._unit:
            # Oblique wind: the subaperture passes a ridge |f_w| ~ |f_u| (one sinc factor stays ~1), so the aliases
            # must reach the along-wind band.
            n_aliases += math.ceil(self.n_modes / (self.n_fine * self.fine_m) * self.line_spacing_m)
        key = (r0_m, r0_wavelength_m, outer_scale_m, kernel, self.pitch_m, self.line_spacing_m, tuple(self._unit),
               n_aliases, self.n_fine * self.fine_m, self.n_lattice)
        shared = (self.n_modes + 1) * self.n_lattice * 4 <= _MAX_SHARED_VARIANCE_BYTES
        variance = _shared_variance_nm2(*key, 0, self.n_modes + 1) if shared else None
        # Field = sqrt(2) Re sum_q A(q) exp(-i 2 pi q p / n_fine) over q in [-n_modes, n_modes], p in fine samples.
        q_all = np.arange(-self.n_modes, self.n_modes + 1)
        spectrum = np.empty((self.n_lines, len(q_all)), dtype=np.complex64)
        chunk = max(1, _FREQUENCY_CHUNK_ELEMENTS // self.n_lattice)
        for first in range(0, len(q_all), chunk):
            q = q_all[first: first + chunk]
            if shared:
                rows = variance[np.abs(q)]
            else:
                low, high = int(np.abs(q).min()), int(np.abs(q).max()) + 1
                rows = lattice_variance_nm2(*key, low, high)[np.abs(q) - low]
            # Single precision draws: the field is exactly the Fourier series of whatever coefficients are drawn.
            draws = self._rng.standard_normal((len(q), self.n_lattice, 2), dtype=np.float32).view(np.complex64)[..., 0]
            coefficients = np.sqrt(rows / 2) * draws  # E|c|² = variance
            lines = np.fft.ifft(coefficients, axis=1)[:, : self.n_lines] * self.n_lattice  # (q, lines)
            deconvolve = 1 / spreading_kernel_transform(q / self.n_fine)
            spectrum[:, first: first + len(q)] = (lines * deconvolve[:, None].astype(np.float32)).T
        series = np.empty((self.n_lines, self.n_fine))
        padded = np.zeros(self.n_fine, dtype=np.complex128)
        for j in range(self.n_lines):  # one line at a time: the zero-padded spectrum is as large as the series
            padded[q_all % self.n_fine] = spectrum[j]
            series[j] = np.sqrt(2) * np.fft.fft(padded).real
        return torch.as_tensor(series)

    def _block(self, b: int) -> torch.Tensor:
        """``(block_frames, n_actuators)`` OPD (nm) of frames ``b * block_frames ...``.

        Only the latest block is kept, in one buffer reused block after block (fresh large allocations cost page
        faults that can cost more than the arithmetic).
        """
        size = self._block_frames
        if self._block_index != b:
            if self._buffer is None:
                self._buffer = torch.empty(size, self.n_actuators, dtype=torch.float64)
            n0, step, frames = b * size, self.fine_per_frame, torch.arange(size).unsqueeze(0)
            for line, members, window0, weights in self._lines:
                lo, hi = int(window0.min()) + n0, int(window0.max()) + n0 + size
                hi = min(hi, (self.n_fine - self._window) // step + 1)  # frames past the screen are never returned
                windows = self._series[line, step * lo: step * (hi - 1) + self._window].unfold(0, self._window, step)
                values = weights @ windows.contiguous().T  # (members, windows): each member's series is a row
                values = values.gather(1, ((window0 + n0 - lo).unsqueeze(1) + frames).clamp(max=values.shape[1] - 1))
                if isinstance(members, slice):
                    self._buffer[:, members] = values.T
                else:
                    self._buffer.index_copy_(1, members, values.T)
            self._block_index = b
        return self._buffer

    def write_frames(self, start: int, stop: int, out: torch.Tensor, add: bool = False) -> torch.Tensor:
        """Write (or, with ``add``, add) the OPD (nm) of frames ``start..stop-1`` into ``out`` ``(frames, n_act)``."""
        require(stop <= self.screen_frames,
                f"frame {stop - 1} is beyond the exact screen (screen_frames={self.screen_frames}): raise "
                "atmosphere.screen_frames")
        size = self._block_frames
        for b in range(start // size, -(-stop // size)):
            lo, hi = max(start - b * size, 0), min(stop - b * size, size)
            rows = out[b * size + lo - start: b * size + hi - start]
            block = self._block(b)[lo:hi]
            rows.add_(block) if add else rows.copy_(block)
        return out

    def frames(self, start: int, stop: int, basis: torch.Tensor | None = None) -> torch.Tensor:
        """OPD (nm) of frames ``start..stop-1`` at the actuators, ``(frames, n_actuators)``; ``basis`` projected out."""
        out = self.write_frames(start, stop, torch.empty(stop - start, self.n_actuators, dtype=torch.float64))
        return out if basis is None else project_out(out, basis)


def project_out(frames: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """Remove the orthonormal ``(n_actuators, m)`` ``basis`` from every frame, in place; returns ``frames``."""
    return frames.addmm_(frames @ basis, basis.T, alpha=-1)
