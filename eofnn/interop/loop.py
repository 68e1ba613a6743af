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
really applied), reach it through a thin adapter (:func:`~eofnn.interop.controls.loop_controller`; the controllers
live in :mod:`eofnn.interop.controls`): :class:`IntegratorControl` (eofnn's
:class:`~eofnn.control.baselines.Integrator` plus white dither for recording), :class:`FilterControl` (an exported
:class:`eofnn.runtime.PredictiveFilter`, the code a real-time computer runs), :class:`SplitControl`, and
:class:`TorchControl` (any eofnn :class:`~eofnn.control.predictive.PredictiveController`, handed to the loop as it
is).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from eofnn.errors import ConfigError, ShiftWarning, require
from eofnn.evaluation.metrics import LoopMetrics, loop_metrics
from eofnn.interop.controls import (
    FilterControl,
    IntegratorControl,
    NumpyController,
    SplitControl,
    TorchControl,
    check_command,
    loop_controller,
    pol_modes,
    runtime_filter,
)
from eofnn.interop.shift import warn_loop_shift
from eofnn.sim.loop.runner import LoopInput, LoopResult
from eofnn.telemetry.record import Telemetry
from eofnn.validation import COUNT, check_value

#: The controllers, with the loop (:mod:`eofnn.interop.controls` holds them).
__all__ = ["DIVERGENCE_FACTOR", "MAX_EXTRA_GAINS", "FilterControl", "IntegratorControl", "LoopRecord", "NumpyController",
           "SimulatorAdapter", "SplitControl", "TorchControl", "check_command", "loop_controller", "pol_modes",
           "require_recorded", "run_closed_loop", "runtime_filter", "scan_integrator", "with_slope_noise"]

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


def with_slope_noise(sim: SimulatorAdapter, noise_nm: float, seed: int) -> SimulatorAdapter:
    """``sim`` with white slope noise added to every measurement after its reconstructor ``sim.reconstructor``
    (``(actuators, slopes)``), scaled so that it leaves ``noise_nm`` RMS per actuator on average; drawn from
    ``numpy.random.default_rng(seed)``. Wraps ``sim.advance`` in place and returns ``sim``."""
    reconstructor = sim.reconstructor
    sigma = noise_nm / float(np.sqrt(np.mean(np.diag(reconstructor @ reconstructor.T))))
    rng, advance = np.random.default_rng(seed), sim.advance

    def noisy(command):
        measurement, rms = advance(command)
        return measurement + reconstructor @ (sigma * rng.standard_normal(reconstructor.shape[1])), rms

    sim.advance = noisy
    return sim
