"""Controllers for another simulator's loop (:func:`eofnn.interop.loop.run_closed_loop`) and the thin adapters that
let it run eofnn's controller protocol (:class:`~eofnn.sim.loop.kernel.Controller`) for every one of them: numpy
controllers (``reset(n_actuators)``, ``step(measurement) -> command``) through :class:`NumpyController`, a
:class:`TorchControl`'s predictive controller as it is."""

from __future__ import annotations

import inspect

import numpy as np
import torch

from eofnn.control.baselines import Integrator
from eofnn.control.predictive import PredictiveController
from eofnn.data.history import HistorySpec, pseudo_open_loop
from eofnn.errors import ConfigError, require
from eofnn.models.linear import LinearFilter
from eofnn.runtime import PredictiveFilter
from eofnn.sim.loop.runner import Controller, LoopInput
from eofnn.telemetry.record import Telemetry
from eofnn.training.export import filter_coefficients, filter_taps
from eofnn.validation import FRACTION, Interval, check_value


def check_command(command_nm, n_actuators: int, what: str = "command") -> np.ndarray:
    """``(K,)`` finite float64, or one :class:`ConfigError` line naming the size and what is allowed."""
    command = np.asarray(command_nm, dtype=np.float64)
    if command.shape != (n_actuators,):
        raise ConfigError(f"{what} has shape {command.shape}: the simulator has {n_actuators} actuators, so it must "
                          f"be ({n_actuators},) nm")
    if not np.isfinite(command).all():
        raise ConfigError(f"{what} holds {int((~np.isfinite(command)).sum())} non-finite value(s): the loop diverged "
                          "or the controller is broken")
    return command


def _check_filter_size(runtime: PredictiveFilter, n_actuators: int) -> None:
    if runtime.n_actuators != n_actuators:
        raise ConfigError(f"the filter has {runtime.n_actuators} actuators but the simulator has {n_actuators}: fit "
                          "it on telemetry of this simulator")


class NumpyController:
    """A controller of the numpy protocol (``reset(n_actuators)``, ``step(measurement) -> command``, optionally
    ``applied(command)``) as an eofnn :class:`~eofnn.sim.loop.kernel.Controller` of batch 1: the measurement it gets
    is ``inp.wfs[0]`` as a numpy array, its command goes back as a ``(1, K)`` tensor, as they are."""

    def __init__(self, control) -> None:
        self.control = control

    def reset(self, batch: int, n_actuators: int, delay_frames: int | float, dtype: torch.dtype) -> None:
        require(batch == 1, f"batch={batch} is invalid for {type(self.control).__name__}: a numpy controller closes one "
                            "loop at a time (batch 1)")
        self.control.reset(n_actuators)

    def step(self, inp: LoopInput) -> torch.Tensor:
        return torch.from_numpy(np.asarray(self.control.step(inp.wfs[0].numpy()), dtype=np.float64))[None]

    def applied(self, command: np.ndarray) -> None:
        """What the loop really applied (projected), for a controller that reads it back."""
        if hasattr(self.control, "applied"):
            self.control.applied(command)


class _WithDelay:
    """An eofnn controller reset with the delay it was made for (a :class:`TorchControl`'s)."""

    def __init__(self, controller: Controller, delay_frames: int | float) -> None:
        self.controller, self.delay_frames = controller, delay_frames

    def reset(self, batch: int, n_actuators: int, delay_frames: int | float, dtype: torch.dtype) -> None:
        self.controller.reset(batch, n_actuators, self.delay_frames, dtype)

    def step(self, inp: LoopInput) -> torch.Tensor:
        return self.controller.step(inp)


def loop_controller(controller) -> Controller:
    """``controller`` as the loop runs it: an eofnn :class:`~eofnn.sim.loop.kernel.Controller` as it is (its
    ``reset`` takes the batch, actuators, delay and dtype), one that names its own (``loop_controller()``: a
    :class:`TorchControl`'s predictive controller), or a numpy one through :class:`NumpyController`."""
    own = getattr(controller, "loop_controller", None)
    if callable(own):
        return own()
    try:
        takes = len(inspect.signature(controller.reset).parameters)
    except (AttributeError, TypeError, ValueError):
        raise ConfigError(f"{type(controller).__name__} is not a controller: it needs reset() and step() (eofnn's "
                          "reset(batch, n_actuators, delay_frames, dtype) / step(LoopInput), or numpy's "
                          "reset(n_actuators) / step(measurement))") from None
    return controller if takes >= 4 else NumpyController(controller)


class IntegratorControl:
    """eofnn's :class:`~eofnn.control.baselines.Integrator`, ``y(n) = y(n-1) - gain * m(n)`` on the delayed
    measurement ``m``, on numpy arrays, plus white dither of ``dither_nm`` RMS that is not fed back into the
    integrator state (as :class:`eofnn.control.baselines.Dithered`, drawn by numpy from ``seed``)."""

    def __init__(self, gain: float, dither_nm: float = 0.0, seed: int = 0) -> None:
        check_value("dither_nm", dither_nm, Interval(0, 1e5, unit="nm"))
        self.integrator = Integrator(float(gain))
        self.gain, self.dither_nm, self.seed = float(gain), float(dither_nm), seed

    def reset(self, n_actuators: int) -> None:
        self.integrator.reset(1, n_actuators, 1, torch.float64)
        self._rng = np.random.default_rng(self.seed)
        self._frame = 0

    def step(self, measurement: np.ndarray) -> np.ndarray:
        m = torch.from_numpy(np.asarray(measurement, dtype=np.float64))[None]
        state = self.integrator.step(LoopInput(self._frame, m, torch.zeros_like(m)))[0].numpy()
        self._frame += 1
        if not self.dither_nm:
            return state.copy()
        return state + self.dither_nm * self._rng.standard_normal(len(state))


class FilterControl:
    """An :class:`eofnn.runtime.PredictiveFilter` as the simulator's controller (plus white dither of ``dither_nm``
    RMS when recording telemetry for a refit: the filter reads back what was applied, dither included).

    The first ``warmup_frames`` frames are closed by an integrator of gain ``warmup_gain`` while the filter reads
    the same measurements and the commands really applied (``y_last``), so that it takes over with full, true
    histories instead of from a flat DM (its first ``first_frame`` commands would be zero otherwise).
    """

    def __init__(self, runtime: PredictiveFilter, warmup_gain: float = 0.3, warmup_frames: int = 0,
                 dither_nm: float = 0.0, seed: int = 0, conditions: dict | None = None) -> None:
        check_value("warmup_frames", warmup_frames, Interval(0, None, integer=True, unit="frames"))
        self.runtime, self.warmup_frames = runtime, warmup_frames
        #: The conditions the filter was trained in (a checkpoint's ``info["conditions"]``), or ``None``: the loop
        #: warns in one line when its own differ (:mod:`eofnn.interop.shift`).
        self.trained_conditions = conditions
        self._warmup = IntegratorControl(warmup_gain)
        self._dither = IntegratorControl(0.0, dither_nm, seed)  # white dither alone (a zero-gain integrator)

    def reset(self, n_actuators: int) -> None:
        _check_filter_size(self.runtime, n_actuators)
        self.runtime.reset()
        self._warmup.reset(n_actuators)
        self._dither.reset(n_actuators)
        self._frame, self._last = 0, None

    def step(self, measurement: np.ndarray) -> np.ndarray:
        y = self.runtime.step(measurement, y_last=self._last)
        if self._frame < self.warmup_frames:
            y = self._warmup.step(measurement)
        self._frame += 1
        return y + self._dither.step(measurement) if self._dither.dither_nm else y

    def applied(self, command: np.ndarray) -> None:
        """What the loop really applied (projected): the filter's next ``y_last``."""
        self._last = command


class TorchControl:
    """An eofnn :class:`~eofnn.control.predictive.PredictiveController` (any torch network) as the controller;
    ``conditions``: those its predictor was trained in (:meth:`from_predictor` takes them from the checkpoint), which
    the loop compares with its own (:mod:`eofnn.interop.shift`)."""

    def __init__(self, controller: PredictiveController, delay_frames: int, conditions: dict | None = None) -> None:
        self.controller, self.delay_frames, self.trained_conditions = controller, delay_frames, conditions

    @classmethod
    def from_predictor(cls, predictor, delay_frames: int, dm_gain_model: float | None = None,
                       name: str = "the predictor") -> TorchControl:
        """A trained predictor (:func:`eofnn.training.checkpoint.load_predictor`) as the controller, with the
        conditions its checkpoint recorded; ``name`` (e.g. the checkpoint's path) names it in a shift warning."""
        control = cls(predictor.controller(dm_gain_model), delay_frames, predictor.info.get("conditions"))
        control.name = name
        return control

    def loop_controller(self) -> Controller:
        """The predictive controller itself, as the loop runs it (reset with this delay)."""
        return _WithDelay(self.controller, self.delay_frames)

    def reset(self, n_actuators: int) -> None:
        self.controller.reset(1, n_actuators, self.delay_frames, torch.float64)
        self._frame, self._zeros = 0, torch.zeros(1, n_actuators, dtype=torch.float64)

    def step(self, measurement: np.ndarray) -> np.ndarray:
        inp = LoopInput(self._frame, torch.from_numpy(np.asarray(measurement, dtype=np.float64))[None], self._zeros)
        self._frame += 1
        return self.controller.step(inp)[0].numpy()


class SplitControl:
    """A predictive filter on the modes where prediction pays, the integrator on the rest.

    ``modes`` ``(K, M)`` (orthonormal columns) span what ``runtime`` (an :class:`eofnn.runtime.PredictiveFilter`)
    commands; the integrator of ``gain`` commands the orthogonal complement, ``y(n) = i(n) + mix B Bᵀ (f(n) - i(n))``
    with ``i(n) = y(n-1) - gain m(n)`` (``y(n-1)`` the command really applied) and ``f(n)`` the filter's command:
    ``mix`` (0 to 1) is the share of the filter's command on its modes, the rest the integrator's (a smaller share
    lowers the bandwidth at which the filter passes what it predicts of the aliasing).
    The filter reads every measurement and applied command, so its histories are whole wherever it acts. The first
    ``warmup_frames`` frames are the integrator's alone. ``M = K``: the filter everywhere; ``M = 0``: the integrator.

    With a Shack-Hartmann and a zonal reconstructor the lowest-order modes carry the most propagated aliasing
    (their singular values are the smallest), which a filter fitted to predict the measurement predicts too;
    :func:`pol_modes` orders the modes so that the integrator can keep the lowest ones (``docs/interop.md``).
    """

    def __init__(self, runtime: PredictiveFilter, modes: np.ndarray, gain: float, warmup_frames: int = 0,
                 mix: float = 1.0) -> None:
        check_value("integrator gain", gain, Interval(0, 10))
        check_value("mix", mix, FRACTION)
        check_value("warmup_frames", warmup_frames, Interval(0, None, integer=True, unit="frames"))
        modes = np.asarray(modes, dtype=np.float64)
        if modes.ndim != 2 or modes.shape[0] != runtime.n_actuators or modes.shape[1] > modes.shape[0]:
            raise ConfigError(f"modes have shape {modes.shape}: they must be ({runtime.n_actuators}, M) with "
                              f"M <= {runtime.n_actuators}, one column per mode the filter commands")
        self.runtime, self.modes, self.gain, self.warmup_frames = runtime, modes, float(gain), warmup_frames
        self.mix = float(mix)

    def reset(self, n_actuators: int) -> None:
        _check_filter_size(self.runtime, n_actuators)
        self.runtime.reset()
        self._last, self._frame = np.zeros(n_actuators), 0

    def step(self, measurement: np.ndarray) -> np.ndarray:
        predicted = self.runtime.step(measurement, y_last=self._last)
        integrated = self._last - self.gain * measurement
        self._frame += 1
        if self._frame <= self.warmup_frames or not self.modes.shape[1]:
            return integrated
        return integrated + self.mix * (self.modes @ (self.modes.T @ (predicted - integrated)))

    def applied(self, command: np.ndarray) -> None:
        self._last = command


def pol_modes(telemetry: Telemetry, dm_gain: float) -> np.ndarray:
    """``(K, K)`` orthonormal modes of the pseudo-open-loop residual ``wfs - dm_gain y`` of ``telemetry`` (its
    principal components, a measured Karhunen-Loeve basis: smooth modes first), by decreasing variance."""
    pol = pseudo_open_loop(telemetry.wfs.double(), telemetry.y.double(), float(dm_gain)).numpy()
    pol = pol - pol.mean(0)
    variance, modes = np.linalg.eigh(pol.T @ pol / max(len(pol) - 1, 1))
    return modes[:, np.argsort(variance)[::-1]]


def runtime_filter(network: LinearFilter, spec: HistorySpec, dm_gain_model: float = 1.0) -> PredictiveFilter:
    """The exported filter of ``network`` (what :func:`eofnn.training.export.export_filter` writes), in memory."""
    if not isinstance(network, LinearFilter):
        raise ConfigError(f"only linear filters run in eofnn.runtime, not {type(network).__name__}: use TorchControl")
    coefficients, neighbours = filter_coefficients(network)
    return PredictiveFilter(coefficients, filter_taps(spec), spec.delay_frames, dm_gain_model, neighbours)
