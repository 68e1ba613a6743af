"""Exact frozen flow along any wind direction: a von Kármán screen evaluated where each actuator looks, every frame.

A wind along a lattice direction of the grid keeps the actuators on a few lines parallel to it
(:class:`~eofnn.sim.atmosphere.exact.ExactFrozenFlow`); any other direction puts every actuator on a line of its own. This
module handles those directions (and any other positions), with the same physics: one layer is a Fourier series in
its own frame (``u`` along the wind, ``w`` across it), with HCIPy's von Kármán spectrum times the sensing kernel's
squared transform as the variance of each coefficient, and frame ``n`` at actuator ``k`` is that series at
``(u_k - n v dt, w_k)``. Nothing is interpolated between frames.

*Along the wind* the series is periodic over ``P = M v dt`` (``M`` whole frames, longer than the screen plus the
aperture and than ``_PERIOD_OUTER_SCALES`` outer scales) and holds the frequencies ``q / P`` up to ``f_max`` (as the
lattice model: twice the frame rate's Nyquist ``1 / (2 v dt)``, at least ``_SPATIAL_BAND / pitch``). Because the
frame step is ``P / M``, the frames of one actuator are ``sqrt(2) Re sum_m B_k(m) exp(-2 pi i m n / M)`` with
``B_k(m)`` the sum over ``q = m (mod M)`` of the actuator's along-wind coefficients times ``exp(2 pi i q u_k / P)``
(the phase ramp of frozen flow): one FFT of length ``M`` gives every frame of every actuator, exactly.

*Across the wind*, for each along-wind frequency ``q`` the actuators' coefficients are
``sum_l c(q, l) exp(2 pi i l w_k / W_q)``: a type-2 non-uniform FFT (FINUFFT, many vectors at the same points).
At fixed ``f_u`` the across-wind covariance decays as ``exp(-2 pi kappa |dw|)``, ``kappa = sqrt(f_u² + L0^-2)``,
so the across-wind period only has to exceed the actuators' spread by ``_IMAGE_DECAY / kappa`` (periodic images
below ``exp(-2 pi _IMAGE_DECAY)``, 7e-9, of the covariance): ``3 L0`` for the lowest frequencies, a few pitches for
most. The across-wind band is ``max(_ACROSS_BAND / pitch, min(_RIDGE |f_u|, _ACROSS_CAP / pitch))``: the subaperture's
transform ``sinc(d f_x) sinc(d f_y)`` keeps a ridge where one factor is ~1, at ``|f_w| = |f_u| cot`` or
``tan`` of the wind angle, and the ridge sets the temporal PSD at high frequencies (tests/test_anywind.py checks the
screen's expected PSD against theory at 17, 30 and 120 degrees; the sweep over directions: ``docs/findings.md``). Each
coefficient has the variance of its frequency cell, ``Phi |K|² / (P W_q)``; frequencies ``q > 0`` carry those of
``-q`` too (the field is ``sqrt(2) Re`` of a complex series).

The whole screen (``screen_frames x n_actuators``, float32: rounding 6e-8 of the RMS, far below any floor a
predictor reaches) is computed when the layer is built, so frames are then copies; set-up time and memory grow as
``screen_frames x n_actuators`` (about ``8 bytes`` per actuator-frame at the peak, refused up front when it does
not fit: :func:`eofnn.resources.require_memory`).
"""

from __future__ import annotations

import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from eofnn.errors import require
from eofnn.lazy import lazy_module
from eofnn.resources import available_memory_bytes, require_memory
from eofnn.sim.atmosphere.exact import (
    _PERIOD_OUTER_SCALES,
    _SPATIAL_BAND,
    _TEMPORAL_BAND,
    VON_KARMAN_COEFFICIENT,
    ExactFrozenFlow,
    lattice_direction,
    nice_fft_size,
)
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.sensing.kernels import KERNELS, apply_kernel_amplitude_

torch = lazy_module("torch")

#: Across-wind band (cycles per pitch): at least ``_ACROSS_BAND``, else ``_RIDGE |f_u|`` up to ``_ACROSS_CAP``.
_ACROSS_BAND = {"subaperture": 4.0, "point": 10.0}
_RIDGE = {"subaperture": 2.0, "point": 3.0}
_ACROSS_CAP = {"subaperture": 16.0, "point": 24.0}
#: Across-wind period beyond the actuators' spread, in units of 1 / kappa (covariance images < exp(-2 pi 3)).
_IMAGE_DECAY = 3.0
#: Across-wind periods are rounded up to powers of this factor, and mode counts to multiples of ``_MODE_STEP``, so
#: that runs of consecutive ``q`` share one non-uniform FFT plan.
_PERIOD_GROWTH = 1.25
_MODE_STEP = 16
#: FINUFFT's requested relative accuracy, in single precision (the screen is float32; against a double-precision
#: transform: ``docs/findings.md``), and its threads: one, as OpenMP threads contending with other processes for few
#: cores were far slower (and one thread is bit-for-bit reproducible).
_NUFFT_EPS = 1e-6
_NUFFT_THREADS = 1
#: Elements (rows x modes or rows x actuators) processed together: bounds the set-up's working memory (~100 MB).
_CHUNK_ELEMENTS = 2**22
#: Amplitude tables up to this size are kept and shared by the realisations of a layer; up to
#: ``_SHARED_AMPLITUDE_TABLES`` of them (one per layer of a two-layer sky: realisations alternate between the layers),
#: the least recently used dropped first.
_MAX_SHARED_AMPLITUDE_BYTES = 256 * 2**20
_SHARED_AMPLITUDE_TABLES = 2
_AMPLITUDE_CACHE: dict[tuple, list] = {}
#: Built screens shared by the layers that ask for the same realisation (least recently used dropped first), up to
#: ``_SCREEN_CACHE_BYTES`` and ``_SCREEN_CACHE_FRACTION`` of the memory available when one is added.
_SCREEN_CACHE: dict[tuple, AnyWindFrozenFlow] = {}
_SCREEN_CACHE_BYTES = 2 * 2**30
_SCREEN_CACHE_FRACTION = 0.25
#: Guards the caches above: :func:`build_screens` builds screens in threads.
_LOCK = threading.RLock()
#: Most screens built at once by :func:`build_screens` (also bounded by the cores this process may use and memory).
_MAX_BUILD_THREADS = 4


def frozen_flow_layer(grid: ActuatorGrid, r0_m: float, r0_wavelength_m: float, outer_scale_m: float,
                      wind_speed_mps: float, wind_direction_deg: float, frame_period_s: float, kernel: str,
                      screen_frames: int, seed: np.random.SeedSequence):
    """One realisation of one ``exact`` layer: the lattice model along lattice directions (fast, pinned by tests),
    :class:`AnyWindFrozenFlow` along any other."""
    if lattice_direction(wind_direction_deg) is not None:
        return ExactFrozenFlow(grid, r0_m, r0_wavelength_m, outer_scale_m, wind_speed_mps, wind_direction_deg,
                               frame_period_s, kernel, screen_frames, seed)
    # A built screen is read-only (frames are copies of it), and a study asks for the same realisation many times
    # (every controller's test stream, every gain of an integrator's scan): built once, it is shared.
    positions = np.ascontiguousarray(grid.positions_m, dtype=float)
    key = (positions.shape, positions.tobytes(), float(grid.pitch_m), r0_m, r0_wavelength_m, outer_scale_m,
           wind_speed_mps, wind_direction_deg, frame_period_s, kernel, screen_frames, seed.entropy,
           tuple(seed.spawn_key), seed.pool_size)
    with _LOCK:
        if key in _SCREEN_CACHE:
            _SCREEN_CACHE[key] = _SCREEN_CACHE.pop(key)  # most recently used last
            return _SCREEN_CACHE[key]
    layer = AnyWindFrozenFlow(grid, r0_m, r0_wavelength_m, outer_scale_m, wind_speed_mps, wind_direction_deg,
                              frame_period_s, kernel, screen_frames, seed)
    _remember_screen(key, layer)
    return layer


def build_screens(calls: list[tuple]) -> list:
    """``[frozen_flow_layer(*args) for args in calls]``, the non-lattice screens among them built side by side in
    threads (FINUFFT, numpy's generator and torch release the GIL): each screen is drawn from its own seed, so the
    numbers are those of building them one after the other. Threads: at most the cores this process may use,
    :data:`_MAX_BUILD_THREADS`, and as many screens' peak memory as a quarter of the memory available holds."""
    costly = [i for i, args in enumerate(calls) if lattice_direction(args[5]) is None]
    out: list = [None] * len(calls)
    threads = 1
    if len(costly) > 1:
        grid, _, _, outer_scale_m, speed, direction, period, _, frames, _ = calls[costly[0]]
        peak = max(1, screen_bytes(grid, outer_scale_m, speed, direction, period, frames))
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        threads = max(1, min(len(costly), cores, _MAX_BUILD_THREADS, int(0.25 * available_memory_bytes() // peak)))
    if threads > 1:
        with ThreadPoolExecutor(threads) as pool:
            for i, layer in zip(costly, pool.map(lambda args: frozen_flow_layer(*args), [calls[i] for i in costly]),
                                strict=True):
                out[i] = layer
    for i, args in enumerate(calls):
        if out[i] is None:
            out[i] = frozen_flow_layer(*args)
    return out


def _remember_screen(key: tuple, layer: AnyWindFrozenFlow) -> None:
    """Keep ``layer`` among the shared screens, dropping the least recently used beyond the cache's budget."""
    budget = min(_SCREEN_CACHE_BYTES, _SCREEN_CACHE_FRACTION * available_memory_bytes())
    size = layer.screen_nbytes
    if size > budget:
        return
    with _LOCK:
        _SCREEN_CACHE[key] = layer
        while sum(lay.screen_nbytes for lay in _SCREEN_CACHE.values()) > budget:
            _SCREEN_CACHE.pop(next(iter(_SCREEN_CACHE)))


def screen_bytes(grid: ActuatorGrid, outer_scale_m: float, wind_speed_mps: float, wind_direction_deg: float,
                 frame_period_s: float, screen_frames: int) -> int:
    """Peak memory (bytes) of building one :class:`AnyWindFrozenFlow` realisation on ``grid`` (0 for a lattice
    direction, whose lines model needs far less): checked up front, before anything is simulated."""
    if lattice_direction(wind_direction_deg) is not None:
        return 0
    angle = math.radians(wind_direction_deg)
    u = grid.positions_m @ np.array([math.cos(angle), math.sin(angle)])
    step_m = wind_speed_mps * frame_period_s
    frames = math.ceil(float(np.ptp(u)) / step_m) + screen_frames + 1
    n_period = nice_fft_size(max(frames, math.ceil(_PERIOD_OUTER_SCALES * outer_scale_m / step_m)))
    return _peak_bytes(n_period, screen_frames, grid.n_actuators)


def _peak_bytes(n_period: int, screen_frames: int, n_positions: int) -> int:
    """The folded series' Hermitian half (complex64, ``n_period / 2 + 1`` rows) and the float32 screen, plus one
    chunk's working arrays (about six complex128 arrays of ``_CHUNK_ELEMENTS``) and the shared amplitude table (at
    most ``_MAX_SHARED_AMPLITUDE_BYTES``)."""
    return (8 * (n_period // 2 + 1) * n_positions + 4 * screen_frames * n_positions + 100 * _CHUNK_ELEMENTS
            + _MAX_SHARED_AMPLITUDE_BYTES)


def _runs(rows: np.ndarray, targets: np.ndarray):
    """Yield ``((a, b), (lo, hi), step)``: the increasing ``rows`` split into runs of consecutive rows ``a .. b - 1``
    whose ``targets`` are consecutive too, ``lo .. hi - 1`` upwards (``step`` 1) or downwards (``step`` -1)."""
    if len(rows) == 0:
        return
    t = targets[rows]
    gap = np.diff(rows)
    up, down = (gap == 1) & (np.diff(t) == 1), (gap == 1) & (np.diff(t) == -1)
    start = 0
    while start < len(rows):
        stop, step = start + 1, 0
        if stop < len(rows) and (up[start] or down[start]):
            step = 1 if up[start] else -1
            run = up if step > 0 else down
            while stop < len(rows) and run[stop - 1]:
                stop += 1
        first, last = int(t[start]), int(t[stop - 1])
        yield (int(rows[start]), int(rows[stop - 1]) + 1), (min(first, last), max(first, last) + 1), step or 1
        start = stop


class AnyWindFrozenFlow:
    """One realisation of one layer moving in any direction, seen through a sensing kernel, at given positions.

    Parameters
    ----------
    grid, r0_m, r0_wavelength_m, outer_scale_m, frame_period_s, kernel, screen_frames, seed
        As for :class:`eofnn.sim.atmosphere.exact.ExactFrozenFlow` (``grid`` gives the positions unless ``positions_m`` does).
    wind_speed_mps, wind_direction_deg : float
        Wind speed (m/s, > 0) and direction (degrees from +x towards +y; any finite value).
    positions_m : ndarray, optional
        ``(n, 2)`` positions (m) to evaluate instead of the grid's actuators (tests probe the field with them).
    """

    def __init__(self, grid: ActuatorGrid, r0_m: float, r0_wavelength_m: float, outer_scale_m: float,
                 wind_speed_mps: float, wind_direction_deg: float, frame_period_s: float, kernel: str,
                 screen_frames: int, seed: np.random.SeedSequence, positions_m: np.ndarray | None = None) -> None:
        require(math.isfinite(wind_speed_mps) and wind_speed_mps > 0,
                f"wind_speed_mps={wind_speed_mps!r} is invalid for model 'exact': it must be a finite number > 0 (m/s)")
        require(math.isfinite(wind_direction_deg),
                f"wind_direction_deg={wind_direction_deg!r} is invalid: it must be a finite number (degrees)")
        require(math.isfinite(outer_scale_m),
                f"outer_scale_m={outer_scale_m!r} is invalid for model 'exact': it must be finite (metres)")
        require(kernel in KERNELS, f"kernel={kernel!r} is invalid: allowed are {', '.join(KERNELS)}")
        self.screen_frames, self.pitch_m, self.kernel = screen_frames, grid.pitch_m, kernel
        positions = np.asarray(grid.positions_m if positions_m is None else positions_m, dtype=float)
        self.n_actuators = len(positions)
        angle = math.radians(wind_direction_deg)
        self._unit = np.array([math.cos(angle), math.sin(angle)])
        u = positions @ self._unit
        w = positions @ np.array([-self._unit[1], self._unit[0]])
        self._u, self._w = u - u.min(), w - 0.5 * (w.max() + w.min())
        self._plan(outer_scale_m, wind_speed_mps * frame_period_s)
        require_memory(self.peak_bytes, f"the exact screen of one layer ({self.n_actuators} positions x "
                                        f"{self.n_period} frames, screen_frames={screen_frames})")
        self._spectrum_args = (r0_m, r0_wavelength_m, outer_scale_m)
        self._series = self._synthesise(np.random.default_rng(seed), *self._spectrum_args)

    @property
    def screen_nbytes(self) -> int:
        """Bytes the built screen holds (``screen_frames x n_actuators`` float32)."""
        return self._series.element_size() * self._series.numel()

    def _plan(self, outer_scale_m: float, step_m: float) -> None:
        """Periods and bands: ``n_period`` frames along the wind, and each ``q``'s across-wind period and modes."""
        spread_u, spread_w = float(self._u.max()), float(np.ptp(self._w))
        self.step_m = step_m
        frames_needed = math.ceil(spread_u / step_m) + self.screen_frames + 1
        self.n_period = nice_fft_size(max(frames_needed, math.ceil(_PERIOD_OUTER_SCALES * outer_scale_m / step_m)))
        self.period_m = self.n_period * step_m
        f_max = max(_TEMPORAL_BAND / (2 * step_m), _SPATIAL_BAND / self.pitch_m)
        q = np.arange(math.floor(f_max * self.period_m) + 1)
        f_u = q / self.period_m
        kappa = np.hypot(f_u, 1 / outer_scale_m)
        base = spread_w + 2 * self.pitch_m  # the subaperture widens the covariance's support by up to 2 pitches
        needed = base + _IMAGE_DECAY / kappa
        smallest = float(needed.min())
        level = np.ceil(np.log(needed / smallest) / math.log(_PERIOD_GROWTH) - 1e-9).clip(0)
        across_period = smallest * _PERIOD_GROWTH**level
        band = np.maximum(_ACROSS_BAND[self.kernel], np.minimum(_RIDGE[self.kernel] * f_u * self.pitch_m,
                                                                _ACROSS_CAP[self.kernel])) / self.pitch_m
        modes = np.ceil(band * across_period / _MODE_STEP).astype(np.int64) * _MODE_STEP  # l in [-modes, modes]
        self._f_w_max = band
        # Runs of consecutive q with the same (period, modes): one plan each.
        key = level * 10**7 + modes
        edges = np.flatnonzero(np.diff(key)) + 1
        self._runs = [(int(a), int(b), float(across_period[a]), int(modes[a]))
                      for a, b in zip(np.r_[0, edges], np.r_[edges, len(q)], strict=True)]
        self.n_q = len(q)
        self.n_coefficients = int(sum((b - a) * (2 * m + 1) for a, b, _, m in self._runs))
        self.peak_bytes = _peak_bytes(self.n_period, self.screen_frames, self.n_actuators)

    def _amplitude_key(self, r0_m: float, r0_wavelength_m: float, outer_scale_m: float) -> tuple:
        return (r0_m, r0_wavelength_m, outer_scale_m, self.kernel, self.pitch_m, tuple(self._unit), self.period_m,
                tuple(self._runs), self._f_w_max.tobytes())

    def _amplitudes(self, r0_m: float, r0_wavelength_m: float, outer_scale_m: float) -> list[tuple]:
        """``[(q, across_period_m, amplitude)]``: rows ``q`` of ``sqrt(variance / 2)`` (nm, float32,
        ``(rows, 2 modes + 1)``, across-wind frequencies ``l / across_period_m``, ``l = -modes .. modes``).

        They do not depend on the seed: tables up to ``_MAX_SHARED_AMPLITUDE_BYTES`` are shared by realisations.
        """
        key = self._amplitude_key(r0_m, r0_wavelength_m, outer_scale_m)
        with _LOCK:
            if key in _AMPLITUDE_CACHE:
                _AMPLITUDE_CACHE[key] = _AMPLITUDE_CACHE.pop(key)  # most recently used last
                return _AMPLITUDE_CACHE[key]
        cos, sin = (np.float32(v) for v in self._unit)
        nm2 = VON_KARMAN_COEFFICIENT * r0_m ** (-5 / 3) * (r0_wavelength_m / (2 * np.pi) * 1e9) ** 2
        out = []
        for first, stop, across_period, modes in self._runs:
            rows = max(1, _CHUNK_ELEMENTS // max(2 * modes + 1, self.n_actuators))
            f_w = (torch.arange(-modes, modes + 1, dtype=torch.float64) / across_period).float().unsqueeze(0)
            for a in range(first, stop, rows):
                q = np.arange(a, min(a + rows, stop))
                f_u = torch.as_tensor(q / self.period_m, dtype=torch.float32).unsqueeze(1)
                # Single precision: the weights of a random field need no more. The square root of the variance is
                # taken factor by factor (no pass over the table for it).
                amplitude = (f_u**2 + f_w**2 + outer_scale_m**-2).pow_(-11 / 12)
                apply_kernel_amplitude_(amplitude, self.kernel, self.pitch_m, f_u, f_w, cos, sin)
                amplitude.masked_fill_(f_w.abs() > torch.as_tensor(self._f_w_max[q], dtype=torch.float32)[:, None], 0)
                # q > 0 carries -q too (sqrt(2) Re of the series); q = 0 keeps both signs of l itself.
                scale = nm2 / (self.period_m * across_period) / 2
                amplitude.mul_(torch.where(torch.as_tensor(q) > 0, 2 * scale, scale).sqrt().float().unsqueeze(1))
                out.append((q, across_period, amplitude.numpy()))
        if 4 * self.n_coefficients <= _MAX_SHARED_AMPLITUDE_BYTES:
            with _LOCK:
                while len(_AMPLITUDE_CACHE) >= _SHARED_AMPLITUDE_TABLES:
                    _AMPLITUDE_CACHE.pop(next(iter(_AMPLITUDE_CACHE)))
                _AMPLITUDE_CACHE[key] = out
        return out

    def _synthesise(self, rng: np.random.Generator, r0_m: float, r0_wavelength_m: float,
                    outer_scale_m: float) -> torch.Tensor:
        """``(screen_frames, n_actuators)`` float32 OPD (nm) of every frame at every position."""
        import finufft  # noqa: PLC0415 (only this model needs it)

        m_period, n = self.n_period, self.n_actuators
        # The frames are sqrt(2) Re sum_m B_k(m) exp(-2 pi i m n / M), B_k(m) the sum of the coefficients of the
        # frequencies q = m (mod M) at actuator k: the inverse real FFT of B's Hermitian part, so only that part is
        # accumulated, 2 H(m) = conj B(m) + B(-m) for m = 0 .. M / 2 (half the memory of B).
        half = m_period // 2 + 1
        hermitian = torch.zeros(half, n, dtype=torch.complex64)
        u = torch.as_tensor(self._u)
        chunks = self._amplitudes(r0_m, r0_wavelength_m, outer_scale_m)
        tallest = max(len(q) for q, _, _ in chunks)
        buffer = np.empty((tallest, n), dtype=np.complex64)  # each chunk's transform, written by FINUFFT in place
        # exp(2 pi i j u_k / P) for rows j = 0, 1, ...: one table for every chunk.
        turns = torch.remainder(torch.arange(tallest, dtype=torch.float64).unsqueeze(1) * u / self.period_m, 1.0)
        ramp = torch.polar(torch.ones_like(turns), 2 * math.pi * turns).to(torch.complex64)
        for q, across_period, amplitude in chunks:
            # E|c|² = variance; single precision draws: the field is exactly the series of whatever is drawn.
            draws = rng.standard_normal((*amplitude.shape, 2), dtype=np.float32).view(np.complex64)[..., 0]
            coefficients = draws * amplitude
            # In [-pi, pi] (the spread is below the period); float32 points for FINUFFT's single precision.
            x = (2 * np.pi * self._w / across_period).astype(np.float32)
            rows = len(q)
            finufft.nufft1d2(x, coefficients, out=buffer[:rows].reshape(amplitude.shape[:-1] + (n,)),
                             eps=_NUFFT_EPS, isign=1, nthreads=_NUFFT_THREADS)
            across = torch.from_numpy(buffer[:rows])
            # Frozen flow's phase ramp: frame n reads u_k - n step, so q's coefficient at u_k gains
            # exp(2 pi i q u_k / P), written exp(2 pi i q0 u_k / P) exp(2 pi i j u_k / P) for rows q = q0 + j (the
            # phases in double precision, rounded once to the series' single precision).
            first = torch.remainder(int(q[0]) * u / self.period_m, 1.0)
            across.mul_(ramp[:rows]).mul_(torch.polar(torch.ones_like(first), 2 * math.pi * first).to(torch.complex64))
            m = q % m_period
            mirror = (-m) % m_period
            # Rows q = m (mod M) of the lower half add their conjugate at m, the others themselves at M - m (both at
            # m = 0 and M / 2): all the chunk's lower rows first, then the others, each in the order of q, as runs
            # of consecutive rows (the same additions, in the same order, as one index_add_ of each set).
            for rows_at, targets, conjugate in ((m < half, m, True), (mirror < half, mirror, False)):
                for (a, b), (lo, hi), step in _runs(np.flatnonzero(rows_at), targets):
                    source = across[a:b] if step > 0 else across[a:b].flip(0)
                    hermitian[lo:hi].add_(source.conj() if conjugate else source)
        return self._frames_of(hermitian)

    def _frames_of(self, hermitian: torch.Tensor) -> torch.Tensor:
        """The first ``screen_frames`` frames from twice the Hermitian part of the folded series (``(M / 2 + 1, n)``):
        ``sqrt(2) Re sum_m B_k(m) exp(-2 pi i m n / M) = sqrt(2) M irfft(H)``."""
        m = self.n_period
        hermitian.mul_(0.5 * m * math.sqrt(2))
        series = torch.empty(self.screen_frames, self.n_actuators, dtype=torch.float32)
        columns = max(1, _CHUNK_ELEMENTS // m)
        for a in range(0, self.n_actuators, columns):
            series[:, a: a + columns] = torch.fft.irfft(hermitian[:, a: a + columns], n=m, dim=0)[: self.screen_frames]
        return series

    def expected_psd(self, frame_rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """``(f_hz, psd)``: the expected one-sided temporal PSD (nm²/Hz) of every position's frames, with no sampling
        noise: the screen's line spectrum, frequency ``q`` at ``(q mod M) / M`` of the frame rate (the frames'
        aliasing), ``+f`` and ``-f`` folded onto one side, each line spread over its cell ``frame_rate_hz / M``.
        The same at every position."""
        power = np.zeros(self.n_period)
        for q, _, amplitude in self._amplitudes(*self._spectrum_args):
            np.add.at(power, q % self.n_period, 2 * (amplitude.astype(np.float64) ** 2).sum(1))
        m = np.arange(1, (self.n_period + 1) // 2)
        cell = frame_rate_hz / self.n_period
        return m * cell, (power[m] + power[self.n_period - m]) / cell

    def write_frames(self, start: int, stop: int, out: torch.Tensor, add: bool = False) -> torch.Tensor:
        """Write (or, with ``add``, add) the OPD (nm) of frames ``start..stop-1`` into ``out`` ``(frames, n_act)``."""
        require(stop <= self.screen_frames,
                f"frame {stop - 1} is beyond the exact screen (screen_frames={self.screen_frames}): raise "
                "atmosphere.screen_frames")
        block = self._series[start:stop]
        return out.add_(block) if add else out.copy_(block)

    def frames(self, start: int, stop: int, basis: torch.Tensor | None = None) -> torch.Tensor:
        """OPD (nm) of frames ``start..stop-1`` at the positions, ``(frames, n)``; ``basis`` projected out."""
        from eofnn.sim.atmosphere.exact import project_out  # noqa: PLC0415

        out = self.write_frames(start, stop, torch.empty(stop - start, self.n_actuators, dtype=torch.float64))
        return out if basis is None else project_out(out, basis)
