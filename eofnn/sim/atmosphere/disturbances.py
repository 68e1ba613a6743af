"""Temporal realism beyond frozen flow: telescope vibrations and boiling layers (both off unless asked for).

*Vibrations* (``Scenario.vibrations``) are narrow-band disturbances of one low-order mode each (tip, tilt, focus,
astigmatism, coma: Zernike polynomials of HCIPy sampled at the active actuators, piston removed, normalised to
unit RMS over them), added to the turbulence ``s(n)`` the controllers must cancel. The modal coefficient is either
a stochastic damped oscillator (``damping > 0``: an AR(2) process driven by white noise, poles at
``exp((-zeta +- i sqrt(1 - zeta²)) 2 pi f0 dt)``, the standard model of on-sky vibrations, a Lorentzian-like peak
of full width about ``2 zeta f0``), or a sinusoid of random phase (``damping = 0``). ``amplitude_nm`` is the RMS
over time and over the pupil. Vibrations are added *after* the atmosphere's piston/tip/tilt projection
(``atmosphere.remove_ptt`` removes the atmosphere's tip and tilt, not the telescope's), so a tip vibration is
always seen.

*Boiling* (``Layer.boiling_time_s``, model ``exact`` only) decorrelates a layer's screen itself with an e-folding
time ``tau``: the layer is ``cos(theta(n)) F1(n) + sin(theta(n)) F2(n)``, two independent frozen-flow realisations
of the same layer (same wind) mixed by the angle ``theta`` of a random walk whose steps have variance
``2 dt / tau``. Every frame is exactly a Gaussian screen of the layer's statistics (variance and structure function
unchanged, for any ``theta``), and ``E[cos(theta(n) - theta(m))] = exp(-|n - m| dt / tau)``, so the space-time
covariance is the frozen-flow covariance times ``exp(-|t| / tau)`` — the second-order statistics of an AR(1) of
independent frozen-flow screens with coefficient ``exp(-dt / tau)`` (the statistics every linear predictor sees).
A stress test: a ``tau`` of a few loop delays quickly swamps prediction.

Both processes are made of blocks of ``_BLOCK_FRAMES`` frames, each drawn from its own seed, with the state (the
oscillator's two last values, the walk's angle) carried from block to block and kept at every block boundary: any
frame range, asked for in any order and any chunking, is the same.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from eofnn.errors import require
from eofnn.lazy import lazy_module
from eofnn.seeding import sub_seed
from eofnn.sim.grid import ActuatorGrid
from eofnn.validation import Constraint, Interval, OneOf, from_mapping, validated

torch = lazy_module("torch")
signal = lazy_module("scipy.signal")

#: Vibration modes and their Noll indices (Noll 1976: 2 = tip along x, 3 = tilt along y, 4 = focus, ...).
MODES = {"tip": 2, "tilt": 3, "focus": 4, "astigmatism_45": 5, "astigmatism_0": 6, "coma_y": 7, "coma_x": 8}
#: Frames drawn together from one seed; fixed so that results never depend on how frames are asked for.
_BLOCK_FRAMES = 4096


@dataclass(frozen=True)
@validated
class Vibration:
    """One narrow-band telescope vibration of one mode, added to the disturbance ``s(n)``.

    Parameters
    ----------
    mode : str
        ``tip`` (x), ``tilt`` (y), ``focus``, ``astigmatism_45``, ``astigmatism_0``, ``coma_y`` or ``coma_x``:
        a Zernike polynomial on the pupil, sampled at the active actuators, piston removed, unit RMS over them.
    frequency_hz : float
        Natural frequency of the oscillator in Hz (the peak of the PSD); below the Nyquist frequency
        ``frame_rate_hz / 2``.
    amplitude_nm : float
        RMS of the vibration, over time and over the pupil, in nm.
    damping : float
        Damping ratio ``zeta`` in [0, 1): ``0`` is a sinusoid of random phase; ``> 0`` a white-noise driven damped
        oscillator (AR(2)), whose peak has a full width at half maximum of about ``2 zeta frequency_hz``.
    """

    mode: str = "tip"
    frequency_hz: float = 40.0
    amplitude_nm: float = 10.0
    damping: float = 0.01

    _constraints: ClassVar[dict[str, Constraint]] = {
        "mode": OneOf(tuple(MODES)),
        "frequency_hz": Interval(0, None, closed="neither", unit="Hz, below the Nyquist frequency frame_rate_hz / 2"),
        # 1 mm RMS: far beyond any telescope that still forms an image (turbulence is ~1 um).
        "amplitude_nm": Interval(0, 1e6, unit="nm RMS"),
        "damping": Interval(0, 1, closed="left", unit="damping ratio"),
    }


def build_vibrations(vibrations: Sequence[Vibration | dict] | None, frame_rate_hz: float) -> list[Vibration]:
    """``vibrations`` as a list of :class:`Vibration` (mappings are built), each checked against the Nyquist frequency.

    A one-line :class:`~eofnn.errors.ConfigError` names a bad value.
    """
    require(vibrations is None or isinstance(vibrations, (list, tuple)),
            f"vibrations={vibrations!r} is invalid: give a list of vibrations, e.g. [{{mode: tip, frequency_hz: 40, "
            "amplitude_nm: 20, damping: 0.01}]")
    out = []
    for vib in vibrations or ():
        if isinstance(vib, dict):
            vib = from_mapping(Vibration, vib, "vibration")
        require(isinstance(vib, Vibration), f"vibration {vib!r} is invalid: give a mapping of Vibration fields")
        nyquist = frame_rate_hz / 2
        require(vib.frequency_hz < nyquist, f"frequency_hz={vib.frequency_hz!r} is invalid: a vibration must be below "
                                            f"the Nyquist frequency frame_rate_hz / 2 = {nyquist:g} Hz")
        out.append(vib)
    return out


def mode_shape(grid: ActuatorGrid, mode: str) -> np.ndarray:
    """``(n_actuators,)`` Zernike ``mode`` (see :data:`MODES`) at the active actuators: zero mean, unit RMS."""
    import hcipy  # heavy: imported when a vibration is built

    require(mode in MODES, f"mode={mode!r} is invalid: allowed are {', '.join(MODES)}")
    n, m = hcipy.mode_basis.noll_to_zernike(MODES[mode])
    x, y = grid.positions_m.T
    shape = np.asarray(hcipy.mode_basis.zernike(n, m, grid.diameter_m, hcipy.CartesianGrid(hcipy.UnstructuredCoords(
        [x, y]))), dtype=np.float64)
    shape = shape - shape.mean()
    return shape / np.sqrt(np.mean(shape**2))


def _child(seed: np.random.SeedSequence, *key: int) -> np.random.Generator:
    """A generator of the sub-stream ``key`` of ``seed``."""
    return np.random.default_rng(sub_seed(seed, *key))


class _BlockedSeries:
    """A scalar series of frames ``0, 1, ...`` made block by block, its state at every block boundary kept.

    ``step(block, state)`` returns the block's ``_BLOCK_FRAMES`` values and the state after it; the state before
    block 0 is ``initial``. A block is computed from the nearest kept boundary at or before it.
    """

    def __init__(self, initial: np.ndarray, step: Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]) -> None:
        self._states = {0: initial}
        self._step = step
        self._last: tuple[int, np.ndarray] | None = None

    def _block(self, b: int) -> np.ndarray:
        if self._last is not None and self._last[0] == b:
            return self._last[1]
        known = max(k for k in self._states if k <= b)
        state = self._states[known]
        for k in range(known, b + 1):
            values, state = self._step(k, state)
            self._states[k + 1] = state
        self._last = (b, values)
        return values

    def values(self, start: int, stop: int) -> np.ndarray:
        """The series at frames ``start .. stop - 1``."""
        size = _BLOCK_FRAMES
        parts = [self._block(b)[max(start - b * size, 0): min(stop - b * size, size)]
                 for b in range(start // size, -(-stop // size))]
        return np.concatenate(parts) if parts else np.empty(0)


def _oscillator(vib: Vibration, frame_period_s: float,
                seed: np.random.SeedSequence) -> Callable[[int, int], np.ndarray]:
    """``values(start, stop)`` of one vibration's modal coefficient (nm), stationary from frame 0."""
    rng = _child(seed, 0)
    omega = 2 * math.pi * vib.frequency_hz * frame_period_s  # rad per frame
    if vib.damping == 0:
        phase = rng.uniform(0, 2 * math.pi)
        return lambda start, stop: math.sqrt(2) * vib.amplitude_nm * np.cos(omega * np.arange(start, stop) + phase)
    radius = math.exp(-vib.damping * omega)
    phi1, phi2 = 2 * radius * math.cos(omega * math.sqrt(1 - vib.damping**2)), -radius**2
    # Stationary AR(2) x(n) = phi1 x(n-1) + phi2 x(n-2) + sigma w(n): variance and lag-1 correlation.
    rho1 = phi1 / (1 - phi2)
    sigma = vib.amplitude_nm * math.sqrt((1 + phi2) * ((1 - phi2) ** 2 - phi1**2) / (1 - phi2))
    x1 = vib.amplitude_nm * rng.standard_normal()  # x(-1), then x(-2) given it
    x2 = rho1 * x1 + vib.amplitude_nm * math.sqrt(1 - rho1**2) * rng.standard_normal()
    b, a = [sigma], [1.0, -phi1, -phi2]

    def step(block: int, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return signal.lfilter(b, a, _child(seed, 1, block).standard_normal(_BLOCK_FRAMES), zi=state)

    return _BlockedSeries(signal.lfiltic(b, a, [x1, x2]), step).values


class VibrationSeries:
    """The vibrations of one realisation: ``add_to(out, start, stop)`` adds frames ``start .. stop - 1`` in nm.

    Parameters
    ----------
    vibrations : sequence of Vibration
        The vibrations (checked against the Nyquist frequency of ``frame_period_s``).
    grid : ActuatorGrid
        Where the modes are sampled.
    frame_period_s : float
        Time between frames in seconds.
    seed : SeedSequence
        Seed of this realisation; vibration ``j`` draws from its sub-stream ``j``.
    """

    def __init__(self, vibrations: Sequence[Vibration], grid: ActuatorGrid, frame_period_s: float,
                 seed: np.random.SeedSequence) -> None:
        vibrations = build_vibrations(vibrations, 1 / frame_period_s)
        self._modes = torch.as_tensor(np.stack([mode_shape(grid, vib.mode) for vib in vibrations]))
        self._coefficients = [_oscillator(vib, frame_period_s, sub_seed(seed, j)) for j, vib in enumerate(vibrations)]

    def coefficients(self, start: int, stop: int) -> torch.Tensor:
        """``(frames, n_vibrations)`` modal coefficients (nm) of frames ``start .. stop - 1``."""
        return torch.as_tensor(np.stack([c(start, stop) for c in self._coefficients], axis=1))

    def add_to(self, out: torch.Tensor, start: int, stop: int) -> torch.Tensor:
        """Add the vibrations of frames ``start .. stop - 1`` to ``out`` ``(frames, n_actuators)``, in place."""
        return out.addmm_(self.coefficients(start, stop), self._modes)


class BoilingLayer:
    """One realisation of a boiling ``exact`` layer: two frozen-flow realisations mixed by a random-walk angle.

    Frame ``n`` is ``cos(theta(n)) F1(n) + sin(theta(n)) F2(n)`` with ``theta(n)`` the sum of ``n + 1`` independent
    steps of variance ``2 dt / boiling_time_s`` (see the module docstring): the frozen-flow statistics in every
    frame, and a temporal covariance ``exp(-|t| / boiling_time_s)`` times the frozen flow's.

    Parameters
    ----------
    screens : tuple of two ExactFrozenFlow
        Independent realisations of the layer (same statistics and wind); anything with ``write_frames`` and
        ``n_actuators``.
    boiling_time_s : float
        E-folding time of the screen's decorrelation, in seconds (> 0).
    frame_period_s : float
        Time between frames in seconds.
    seed : SeedSequence
        Seed of the random walk.
    """

    def __init__(self, screens, boiling_time_s: float, frame_period_s: float, seed: np.random.SeedSequence) -> None:
        require(boiling_time_s > 0, f"boiling_time_s={boiling_time_s!r} is invalid: it must be > 0 (s)")
        self._screens = screens
        self.screen_frames = min(s.screen_frames for s in screens)
        self.n_actuators = screens[0].n_actuators
        step_sigma = math.sqrt(2 * frame_period_s / boiling_time_s)

        def step(block: int, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            theta = state[0] + np.cumsum(step_sigma * _child(seed, block).standard_normal(_BLOCK_FRAMES))
            return theta, theta[-1:]

        self._angle = _BlockedSeries(np.zeros(1), step)

    def angle(self, start: int, stop: int) -> np.ndarray:
        """The mixing angle ``theta`` (rad) of frames ``start .. stop - 1``."""
        return self._angle.values(start, stop)

    def write_frames(self, start: int, stop: int, out: torch.Tensor, add: bool = False) -> torch.Tensor:
        """Write (or, with ``add``, add) the OPD (nm) of frames ``start..stop-1`` into ``out`` ``(frames, n_act)``."""
        theta = torch.as_tensor(self.angle(start, stop)).unsqueeze(1)
        first = self._screens[0].write_frames(start, stop, torch.empty_like(out))
        second = self._screens[1].write_frames(start, stop, torch.empty_like(out))
        mixed = first.mul_(theta.cos()).addcmul_(second, theta.sin())
        return out.add_(mixed) if add else out.copy_(mixed)
