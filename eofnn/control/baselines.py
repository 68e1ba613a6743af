"""Baseline controllers: uncorrected, the pseudo-integrator, the leaky integrator, and a dither wrapper."""

from __future__ import annotations

import math

from eofnn.errors import require
from eofnn.lazy import lazy_module
from eofnn.seeding import int_seed, torch_generator
from eofnn.sim.loop.runner import LoopInput, LoopResult, record_loop
from eofnn.sim.scenario import Scenario
from eofnn.validation import Interval, check_value

torch = lazy_module("torch")


class Uncorrected:
    """``y(n) = 0``: the open-loop turbulence."""

    def reset(self, batch: int, n_actuators: int, delay_frames: int, dtype: torch.dtype) -> None:
        self._zeros = torch.zeros(batch, n_actuators, dtype=dtype)

    def step(self, inp: LoopInput) -> torch.Tensor:
        return self._zeros


class PseudoIntegrator:
    """``y(n) = -s(n - d)``: perfect correction ``d`` frames late (the study's baseline; an oracle).

    ``d`` is the whole part of the delay: for a fractional delay ``d + f`` the DM then applies
    ``-((1 - f) s(n - d) + f s(n - d - 1))`` over frame ``n``.
    """

    def reset(self, batch: int, n_actuators: int, delay_frames: int, dtype: torch.dtype) -> None:
        pass

    def step(self, inp: LoopInput) -> torch.Tensor:
        return -inp.turbulence


class Integrator:
    """Leaky integrator ``y(n) = (1 - leak) y(n-1) - gain * m(n - d)`` on the WFS measurement ``m``.

    For a delay of ``d`` frames and a nominal plant the loop is stable for ``gain < 2 sin(pi / (2 (2d - 1)))``
    (1 for the two-frame delay) when ``leak = 0``; see :func:`critical_gain`. It runs unchanged for a fractional
    delay ``d + f`` (it reads ``m(n - d)``); its critical gain is then that of
    :func:`eofnn.analysis.stability.analyse_integrator` (2 for 1.5 frames).
    """

    def __init__(self, gain: float = 0.5, leak: float = 0.0) -> None:
        check_value("integrator gain", gain, Interval(0, 10))
        check_value("integrator leak", leak, Interval(0, 1))
        self.gain, self.leak = gain, leak

    def reset(self, batch: int, n_actuators: int, delay_frames: int, dtype: torch.dtype) -> None:
        self._y = torch.zeros(batch, n_actuators, dtype=dtype)

    def step(self, inp: LoopInput) -> torch.Tensor:
        self._y = (1 - self.leak) * self._y - self.gain * inp.wfs
        return self._y


def critical_gain(delay_frames: int) -> float:
    """Integrator gain at which a loop with ``delay_frames`` of delay becomes unstable (nominal plant, no leak).

    The characteristic polynomial ``z**d - z**(d-1) + k`` has a root on the unit circle at
    ``k = 2 sin(pi / (2 (2d - 1)))``. Integer delays only: a fractional one has no such closed form
    (use :func:`eofnn.analysis.stability.analyse_integrator`).
    """
    require(float(delay_frames).is_integer() and delay_frames >= 1,
            f"delay_frames={delay_frames!r} is invalid: the closed form needs an integer >= 1")
    return 2 * math.sin(math.pi / (2 * (2 * delay_frames - 1)))


class Dithered:
    """Adds white dither of ``amplitude_nm`` RMS to another controller's commands (persistent excitation).

    The dither is part of ``y`` as the DM receives it, so telemetry records it; it also enters the wrapped
    controller's own state only through the measured residuals, as on a real system. With ``modes`` (``(K, M)``
    orthonormal command modes, e.g. Karhunen-Loeve modes) the dither is white on those modes alone,
    ``amplitude_nm`` RMS per mode and frame: a modal dither, from which per-mode gains are identified
    (:mod:`eofnn.training.modal_gains`).
    """

    def __init__(self, controller, amplitude_nm: float, seed: int = 0, modes=None) -> None:
        check_value("dither amplitude_nm", amplitude_nm, Interval(0, 1e5, unit="nm"))
        self.controller, self.amplitude_nm, self.seed = controller, amplitude_nm, seed
        self.modes = None if modes is None else torch.as_tensor(modes, dtype=torch.float64)
        require(self.modes is None or self.modes.ndim == 2,
                "dither modes must be a (actuators, modes) matrix of command modes")

    def reseed(self, seed: int) -> None:
        """Draw the dither from another seed from the next reset on (one per recorded sequence)."""
        self.seed = seed

    def reset(self, batch: int, n_actuators: int, delay_frames: int, dtype: torch.dtype) -> None:
        self.controller.reset(batch, n_actuators, delay_frames, dtype)
        self._gen = torch_generator(self.seed, "dither")
        self._shape, self._dtype = (batch, n_actuators), dtype
        require(self.modes is None or self.modes.shape[0] == n_actuators,
                f"dither modes have {0 if self.modes is None else self.modes.shape[0]} actuators but the loop has "
                f"{n_actuators}")

    def step(self, inp: LoopInput) -> torch.Tensor:
        y = self.controller.step(inp)
        if self.amplitude_nm == 0:
            return y
        if self.modes is None:
            return y + self.amplitude_nm * torch.randn(self._shape, generator=self._gen, dtype=self._dtype)
        coefficients = torch.randn(self._shape[0], self.modes.shape[1], generator=self._gen, dtype=self._dtype)
        return y + self.amplitude_nm * coefficients @ self.modes.T.to(self._dtype)


def record_dithered(scenario: Scenario, data, n_frames: int, streams: tuple[str, str, str], realisations: int = 1, *,
                    progress: bool = False, where: str = "") -> LoopResult:
    """Telemetry (``y``, ``wfs``) recorded in ``scenario``'s plant while an integrator (``data.integrator_gain``) plus
    ``data.dither_nm`` of white dither holds the loop, as a telescope records the telemetry it identifies its plant
    from. ``streams`` names the turbulence stream of ``data.seed`` and the seeds of the dither and the WFS noise
    (``int_seed(data.seed, name)``); a diverged recording is refused in one line (``where``: in which loop)."""
    turbulence, dither, noise = streams
    recorder = Dithered(Integrator(data.integrator_gain), data.dither_nm, int_seed(data.seed, dither))
    return record_loop(scenario.turbulence(data.seed, turbulence, realisations), scenario.plant, recorder, n_frames,
                       noise_seed=int_seed(data.seed, noise), progress=progress, where=where)
