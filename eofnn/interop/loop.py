"""The part every simulator shares: its closed loop with a delay line, controllers as callables, telemetry out.

A simulator adapter (:class:`SimulatorAdapter`: :class:`eofnn.interop.oopao.OopaoLoop`,
:class:`eofnn.interop.hcipy.HcipyLoop`) owns the physics of one frame: it moves its turbulence on by one frame,
applies a command to its DM, propagates, measures with its own sensor and reconstructs the measurement in actuator
space. :func:`run_closed_loop` closes the loop around it the way OOPAO's ``run_cl`` and HCIPy's AO tutorials do,
with eofnn's conventions (``docs/telemetry.md``):

    y(n)    the command applied during frame n, computed from measurements up to frame n - d
    eps(n)  the residual OPD of frame n: turbulence plus what the DM applies of y(n)
    wfs(n)  the simulator's reconstructed measurement of eps(n), in nm on the actuators

so ``d = 2`` is OOPAO's "store the slopes after computing the commands". The recorded ``y`` and ``wfs`` (plus the
actuator positions, delay and frame rate) are an eofnn :class:`~eofnn.telemetry.record.Telemetry`; the residual OPD
RMS per frame (nm, piston removed, over the pupil: the simulator's own number, not eofnn's) is summarised with
eofnn's loop metrics (:func:`eofnn.evaluation.metrics.loop_metrics`: median RMS after the settling frames).

The loop runs eofnn's controller protocol (:class:`~eofnn.sim.loop.kernel.Controller`: ``reset(batch, K, delay,
dtype)``, ``step(LoopInput) -> command``, batch 1, float64), the one :func:`~eofnn.sim.loop.runner.run_loop` runs:
any eofnn controller closes another simulator's loop as it is. Controllers written against numpy, with
``reset(n_actuators)`` and ``step(measurement) -> command`` (nm; and ``applied(command)`` to be told what the loop
really applied), reach it through a thin adapter (:func:`loop_controller`): :class:`IntegratorControl` (eofnn's
:class:`~eofnn.control.baselines.Integrator` plus white dither for recording), :class:`FilterControl` (an exported
:class:`eofnn.runtime.PredictiveFilter`, the code a real-time computer runs), :class:`SplitControl`, and
:class:`TorchControl` (any eofnn :class:`~eofnn.control.predictive.PredictiveController`, handed to the loop as it
is).
"""

from __future__ import annotations

import inspect
import warnings
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from eofnn.control.baselines import Integrator
from eofnn.control.predictive import PredictiveController
from eofnn.data.history import HistorySpec, pseudo_open_loop
from eofnn.errors import ConfigError, ShiftWarning, require
from eofnn.evaluation.metrics import LoopMetrics, loop_metrics
from eofnn.interop.shift import warn_loop_shift
from eofnn.models.linear import LinearFilter
from eofnn.runtime import PredictiveFilter
from eofnn.sim.loop.runner import Controller, LoopInput, LoopResult
from eofnn.telemetry.record import Telemetry
from eofnn.training.export import filter_coefficients, filter_taps
from eofnn.validation import COUNT, FRACTION, Interval, check_value

#: A loop whose residual exceeds this times its first frames' turbulence RMS (or is not finite) has diverged.
DIVERGENCE_FACTOR = 10.0


@runtime_checkable
class SimulatorAdapter(Protocol):
    """One frame of another simulator's AO system, seen in actuator space.

    Attributes
    ----------
    name : str
        The simulator ("oopao", "hcipy").
    positions_m : ndarray
        ``(K, 2)`` actuator (x, y) in metres, in the order of the commands.
    delay_frames : int
        Loop delay ``d``: the command of frame ``n`` uses measurements up to frame ``n - d``.
    frame_rate_hz : float
        Loop frame rate in Hz.
    """

    name: str
    positions_m: np.ndarray
    delay_frames: int
    frame_rate_hz: float

    @property
    def n_actuators(self) -> int:
        """``K``."""

    def reset(self, seed: int) -> None:
        """A new turbulence realisation drawn from ``seed``, a flat DM and fresh noise."""

    def advance(self, command_nm: np.ndarray) -> tuple[np.ndarray, float]:
        """One frame with ``command_nm`` (``(K,)``) on the DM: ``(measurement of this frame's residual, nm on
        the actuators, (K,); residual OPD RMS over the pupil, nm, piston removed)``."""

    def project(self, command_nm: np.ndarray) -> np.ndarray:
        """The command without the modes the sensor does not see (what the loop really applies)."""

    def describe(self) -> dict:
        """The set-up, JSON-ready."""


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


# -- controllers ----------------------------------------------------------------------------------------------
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


# -- the loop -------------------------------------------------------------------------------------------------
@dataclass
class LoopRecord:
    """One closed-loop run in another simulator: ``y``, ``wfs`` (``(frames, K)``, nm) and the residual OPD RMS
    per frame (nm), cut at the frame where it diverged, if it did."""

    y: np.ndarray
    wfs: np.ndarray
    residual_rms_nm: np.ndarray
    positions_m: np.ndarray
    delay_frames: int
    frame_rate_hz: float
    config: dict = field(default_factory=dict)
    diverged_frame: int | None = None
    #: One line per condition (WFS noise, DM gain, wind) in which the loop differs from what the controller's
    #: predictor was trained in (:mod:`eofnn.interop.shift`); empty when none does or nothing is known.
    shift: list[str] = field(default_factory=list)

    def telemetry(self, start: int = 0) -> Telemetry:
        """The recorded ``y`` and ``wfs`` from frame ``start`` on as eofnn telemetry (positions, delay, rate)."""
        return Telemetry(y=torch.from_numpy(self.y[start:]), wfs=torch.from_numpy(self.wfs[start:]),
                         delay_frames=self.delay_frames, frame_rate_hz=self.frame_rate_hz,
                         positions_m=torch.from_numpy(self.positions_m), config=self.config,
                         measurement=self.config.get("measurement", ""))

    def metrics(self, settle_frames: int, wavelength_m: float = 1.65e-6) -> LoopMetrics:
        """eofnn's loop metrics of the residual OPD (median RMS after ``settle_frames``; Strehl at H by default)."""
        rms = torch.from_numpy(self.residual_rms_nm)[None]
        result = LoopResult(Telemetry(), rms, rms, self.diverged_frame is not None, self.diverged_frame)
        return loop_metrics(result, settle_frames, wavelength_m)


def run_closed_loop(sim: SimulatorAdapter, controller, n_frames: int, seed: int, *,
                    divergence_factor: float = DIVERGENCE_FACTOR, observers=()) -> LoopRecord:
    """Close ``sim``'s loop with ``controller`` for ``n_frames`` frames on the turbulence realisation ``seed``.

    Per frame ``n``: the controller (:func:`loop_controller`: eofnn's protocol, batch 1, float64) gets the
    measurement of frame ``n - d`` (zeros before the first; its ``turbulence`` is zeros too: another simulator's
    truth is not the controller's) and returns ``y(n)``; the loop applies ``sim.project(y(n))`` (the modes the
    sensor sees), tells a numpy controller that reads it back (``applied``), and the simulator advances one frame
    with it. A residual above ``divergence_factor`` times the RMS of the first frame (the uncorrected
    turbulence) stops the run as diverged. A controller that carries the conditions its predictor was trained in
    (``trained_conditions``) is compared with the loop's (:func:`eofnn.interop.shift.warn_loop_shift`): the record's
    ``shift`` holds the lines, and the first run of that controller issues them as one warning each. Each of
    ``observers`` is called as ``observer(n, sim)`` after frame ``n`` (to record what only the simulator knows:
    its truth, its residual map).
    """
    check_value("n_frames", n_frames, COUNT)
    k, d = sim.n_actuators, sim.delay_frames
    require(float(d).is_integer() and d >= 1, f"delay_frames={d!r} is invalid: the adapters run integer delays >= 1")
    sim.reset(seed)
    control = loop_controller(controller)
    control.reset(1, k, d, torch.float64)
    zeros = torch.zeros(1, k, dtype=torch.float64)
    pending = [np.zeros(k) for _ in range(int(d))]  # measurements in flight, oldest first
    y_all, wfs_all, rms_all = np.zeros((n_frames, k)), np.zeros((n_frames, k)), np.zeros(n_frames)
    diverged, limit = None, None
    for n in range(n_frames):
        m = torch.from_numpy(np.asarray(pending.pop(0), dtype=np.float64))[None]
        y = control.step(LoopInput(n, m, zeros))
        y = y.detach().cpu().numpy() if isinstance(y, torch.Tensor) else np.asarray(y)
        command = check_command(y[0] if y.ndim == 2 and len(y) == 1 else y, k, f"{type(controller).__name__} command")
        command = sim.project(command)
        if isinstance(control, NumpyController):
            control.applied(command)
        measurement, rms = sim.advance(command)
        for observe in observers:
            observe(n, sim)
        pending.append(measurement)
        y_all[n], wfs_all[n], rms_all[n] = command, measurement, rms
        limit = divergence_factor * max(rms, 1e-9) if limit is None else limit
        if not (np.isfinite(rms) and rms <= limit and np.isfinite(measurement).all()):
            diverged = n
            break
    stop = n_frames if diverged is None else diverged
    record = LoopRecord(y_all[:stop], wfs_all[:stop], rms_all[:stop], np.asarray(sim.positions_m), int(d),
                        float(sim.frame_rate_hz), sim.describe(), diverged)
    if getattr(controller, "trained_conditions", None) is not None:
        with warnings.catch_warnings():
            if getattr(controller, "_shift_said", False):  # said once per controller, recorded in every run
                warnings.simplefilter("ignore", ShiftWarning)
            record.shift = warn_loop_shift(sim, controller, record, stop // 10)
        controller._shift_said = True
    return record


def require_recorded(record: LoopRecord, gain: float, sim: SimulatorAdapter) -> LoopRecord:
    """``record`` of a dithered integrator recording telemetry, or one :class:`ConfigError` line if it diverged."""
    if record.diverged_frame is not None:
        raise ConfigError(f"the recording integrator (gain {gain}) diverged at frame {record.diverged_frame} "
                          f"in {sim.name}'s loop: lower record_gain or dither_nm")
    return record


#: Gains a scan adds past the top of its grid while the best gain is still the highest one tried.
MAX_EXTRA_GAINS = 6


def scan_integrator(sim: SimulatorAdapter, gains, n_frames: int, seed: int, settle_frames: int) -> dict:
    """The simulator's best-gain integrator: each gain in ``gains`` closes the loop on the same realisation
    ``seed``, and while the best is the highest gain tried the scan climbs on by the grid's last step (at most
    :data:`MAX_EXTRA_GAINS` more, until a gain diverges or does worse), so the choice is not the grid's edge unless
    it is the edge of what helps; returns ``{"gain": best, "median_rms_nm": its median, "scan": {gain: median or
    None if diverged}}``."""
    scan = {}

    def run(gain: float) -> None:
        record = run_closed_loop(sim, IntegratorControl(gain), n_frames, seed)
        scan[gain] = record.metrics(settle_frames).median_rms_nm

    for gain in gains:
        run(float(gain))
    stable = {g: v for g, v in scan.items() if v is not None}
    require(bool(stable), f"every integrator gain of {list(scan)} diverged in {sim.name}'s loop: give smaller gains")
    ordered = sorted(scan)
    step = ordered[-1] - ordered[-2] if len(ordered) > 1 else 0.5 * ordered[-1]
    for _ in range(MAX_EXTRA_GAINS):
        best = min(stable, key=stable.get)
        if best != max(scan) or step <= 0:
            break
        run(round(best + step, 6))
        stable = {g: v for g, v in scan.items() if v is not None}
    best = min(stable, key=stable.get)
    return {"gain": best, "median_rms_nm": stable[best], "scan": scan}
