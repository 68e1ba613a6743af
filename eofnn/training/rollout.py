"""The closed loop as a differentiable function of a predictor: what training through the loop descends on.

:func:`rollout` runs a predictor against windows of turbulence through a plant, frame by frame, exactly as
:func:`~eofnn.sim.loop.runner.run_loop` runs a :class:`~eofnn.control.predictive.PredictiveController` (the same
measurements, the same pseudo-open-loop reconstruction, the same histories, zero commands until the history is full,
the plant's own :class:`~eofnn.sim.loop.plant.PlantModel`), but out of place, so that the residuals
``eps(n) = s(n) + DM(y(n))`` carry gradients back to the predictor's weights through every command that fed them.

Truncated backpropagation: the first ``warmup`` frames of a window run without gradients (they bring the loop's state,
from a reset, to where the filter holds it), and :func:`loop_loss` is the mean squared residual of the frames after
them. :class:`~eofnn.training.windows.LoopWindows` cuts the training streams of a fit (the same turbulence, plants and
WFS-noise draws that the closed-form fit learns from) into such windows; :func:`loop_step` is the optimiser step of
:class:`~eofnn.training.task.PredictorTask` on them.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace

import torch
from torch import nn

from eofnn.data.history import HistorySpec
from eofnn.models.build import input_dtype
from eofnn.sim.loop.kernel import Loop, LoopInput, ZonalSensor, is_one, loop_sensor
from eofnn.sim.loop.plant import Plant, PlantModel
from eofnn.training.windows import ROLLOUT_BYTES, LoopBatch, LoopWindow, LoopWindows, joined, merged, window_starts

#: The windows (:mod:`eofnn.training.windows`) beside the rollout that closes the loop over them.
__all__ = ["ROLLOUT_BYTES", "LoopBatch", "LoopWindow", "LoopWindows", "RolloutPredictor", "batch_loss", "closed_loop",
           "joined", "log_loop_residual", "loop_loss", "loop_residual", "loop_step", "merged", "rollout",
           "sensor_measurement", "window_starts"]


class RolloutPredictor:
    """A predictor as a :class:`~eofnn.sim.loop.kernel.Controller` that keeps its histories out of place (lists of
    the frames' tensors), so that every command stays in the graph: what
    :class:`~eofnn.control.predictive.PredictiveController` computes, differentiably.

    Per frame ``n``: the measurement ``wfs(n - d)`` enters the history, as itself (closed loop) or as the
    pseudo-open-loop value ``wfs(n - d) - g_model y_applied(n - d)`` (open loop, ``y_applied`` averaged like the DM
    for a fractional delay); ``y(n)`` is the network's command on ``spec``'s history once it is full (zeros before
    ``spec.first_frame``).
    """

    def __init__(self, network: nn.Module, spec: HistorySpec, dm_gain_model: float = 1.0) -> None:
        self.network, self.spec, self.dm_gain_model = network, spec, dm_gain_model
        self._dtype = input_dtype(network)

    def reset(self, batch: int, n_actuators: int, delay_frames: int | float, dtype: torch.dtype) -> None:
        self._ys: list[torch.Tensor] = []  # y(0), y(1), ...: the commands computed so far
        self._signal: list[torch.Tensor] = []  # what the history reads (POL values or measurements), its last p frames

    def _command(self, lag: int, zero: torch.Tensor) -> torch.Tensor:
        """``y(n - lag)`` for the frame ``n`` being computed (zeros before the reset)."""
        return self._ys[len(self._ys) - lag] if lag <= len(self._ys) else zero

    def step(self, inp: LoopInput) -> torch.Tensor:
        spec, wfs = self.spec, inp.wfs
        p, d, f = spec.history_length, spec.whole_delay, spec.delay_fraction
        zero = torch.zeros_like(wfs)
        if spec.kind == "open_loop":
            applied = (self._command(d, zero) if not f
                       else (1 - f) * self._command(d, zero) + f * self._command(d + 1, zero))
            self._signal.append(wfs - self.dm_gain_model * applied)
        else:
            self._signal.append(wfs)
        if len(self._signal) > p:
            self._signal.pop(0)
        if inp.frame >= spec.first_frame:
            history = torch.stack(self._signal[::-1], dim=-1)
            if spec.kind == "closed_loop":
                past = torch.stack([self._command(lag, zero) for lag in range(1, p + 1)], dim=-1)
                history = torch.cat([past, history], -1)
            y = self.network(history.to(self._dtype)).to(wfs.dtype)
        else:
            y = zero
        self._ys.append(y)
        return y


def rollout(network: nn.Module, spec: HistorySpec, window: LoopWindow) -> torch.Tensor:
    """``(batch, frames, K)`` residuals ``eps`` of ``network`` closing the loop over ``window``, with gradients
    (when enabled) from the frame ``window.warmup`` on.

    The loop is :class:`~eofnn.sim.loop.kernel.Loop`'s step, the one :func:`~eofnn.sim.loop.runner.run_loop` runs,
    out of place, through the window's sensor (its measurement, noise colour and what it reports in the modes it
    cannot see: the Shack-Hartmann's ``(I - P) y``; through its MMSE reconstructor, ``R_mmse`` applied to the
    window's ``sensed`` turbulence and noise, as ``run_loop`` applies it), with the network as a :class:`RolloutPredictor` (what
    :class:`~eofnn.control.predictive.PredictiveController` computes): per frame ``n`` (after the reset at the
    window's first frame) the measurement ``wfs(n - d)`` enters the history, the network's ``y(n)`` goes through the
    DM (``(1 - f) DM(y(n)) + f DM(y(n - 1))`` for a fractional delay), ``eps(n) = s(n) + DM`` and the sensor measures
    it.
    """
    return closed_loop(network, spec, window)[0]


def closed_loop(network: nn.Module, spec: HistorySpec, window: LoopWindow) -> tuple[torch.Tensor, torch.Tensor]:
    """``(eps, dm)``: :func:`rollout`'s residuals and the DM terms acting over each frame, ``(batch, frames, K)``."""
    params = next(network.parameters(), None)
    device = params.device if params is not None else window.s.device
    s = window.s.to(device)
    batch, frames, n_act = s.shape
    plant = window.plant
    dm_gain = plant.dm_gain if window.dm_gains is None else window.dm_gains.to(device)
    wfs_gain = None if window.wfs_gains is None else window.wfs_gains.to(device)
    # The plant's DM up to its gain, which is applied after it (a number, or one per window), as PlantModel applies it.
    model = PlantModel(replace(plant, dm_gain=1.0, dm_gain_drift=None), window.grid, s.dtype).to(device)
    measurement = sensor_measurement(window, plant, dm_gain, wfs_gain).to(device)
    noise = None
    if window.noise is not None and measurement.noisy:
        noise = measurement.noise(window.noise.to(device))  # the whole window's at once, as run_loop's chunk
    sensed = None if window.sensed is None else window.sensed.to(device)  # an MMSE computer's view of s
    controller = RolloutPredictor(network, spec, window.dm_gain_model)
    loop = Loop(model, measurement, controller, dm_gain=None if is_one(dm_gain) else dm_gain, in_place=False)
    loop.reset(batch, n_act, s.dtype, device)
    grad = torch.is_grad_enabled()
    eps_out, dm_out = [], []
    for n in range(frames):
        with torch.set_grad_enabled(grad and n >= window.warmup):
            step = loop.step(n, s[:, n], None if noise is None else noise[:, n],
                             sensed=None if sensed is None else sensed[:, n])
            eps_out.append(step.eps)
            dm_out.append(step.dm)
    return torch.stack(eps_out, dim=1), torch.stack(dm_out, dim=1)


def sensor_measurement(window: LoopWindow, plant: Plant, dm_gain, wfs_gain):
    """The measurement of ``window``'s sensor (the zonal one when it has none; a registered name is built on the
    window's grid) in ``plant`` with these gains."""
    sensor = loop_sensor(window.sensor, window.grid) or ZonalSensor(window.s.shape[-1])
    return sensor.measurement(plant, dm_gain, wfs_gain)


def loop_loss(network: nn.Module, spec: HistorySpec, window: LoopWindow) -> torch.Tensor:
    """Mean squared residual (nm²) of ``network`` in the closed loop over ``window``'s frames after its warm-up: at
    the actuators, or over the pupil (piston removed) when the window has one (a Shack-Hartmann's: what the loop is
    scored on, fitting error and aliasing included)."""
    eps, dm = closed_loop(network, spec, window)
    if window.pupil is None:
        return eps[:, window.warmup:].pow(2).mean()
    device = dm.device
    pupil = {k: v[:, window.warmup:].to(device) for k, v in window.pupil.items()}
    return window.sensor.pupil_mean_square(pupil, dm[:, window.warmup:]).mean()


def batch_loss(network: nn.Module, spec: HistorySpec, batch: LoopBatch, backward=None) -> torch.Tensor:
    """Mean squared residual (nm²) over every window of ``batch``, detached; with ``backward`` (``loss ->
    None``) each window's share is backpropagated as it is computed (one window's graph in memory at a time)."""
    total = batch.samples
    value = torch.zeros((), dtype=torch.float64)
    for window in batch.windows:
        loss = loop_loss(network, spec, window) * (window.samples / total)
        if backward is not None:
            backward(loss)
        value = value + loss.detach().to(value.device, value.dtype)
    return value


@torch.no_grad()
def loop_residual(network: nn.Module, spec: HistorySpec, batches: Iterable[LoopBatch]) -> float:
    """Mean squared closed-loop residual (nm²) of ``network`` over every window of ``batches``."""
    batches = list(batches)
    total = sum(batch.samples for batch in batches)
    return sum(float(batch_loss(network, spec, batch)) * batch.samples for batch in batches) / total


def loop_step(task, batch: LoopBatch) -> torch.Tensor:
    """One optimiser step of ``task`` (a :class:`~eofnn.training.task.PredictorTask` in manual optimisation) on the
    closed-loop residual of ``batch``; logs ``train_loss``.

    A step that leaves non-finite weights or loss (a filter driven so far out of stability that the residual
    overflows) is undone, the optimiser's memory cleared and its learning rate halved, so the next step is shorter.
    """
    optimizer = task.optimizers()
    params = [p for p in task.network.parameters() if p.requires_grad]
    before = [p.detach().clone() for p in params]

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        return batch_loss(task.network, task.spec, batch, task.manual_backward)

    loss = optimizer.step(closure=closure)
    if not (torch.isfinite(loss) and all(bool(torch.isfinite(p).all()) for p in params)):
        with torch.no_grad():
            for param, old in zip(params, before, strict=True):
                param.copy_(old)
        optimizer.optimizer.state.clear()
        for group in optimizer.param_groups:
            group["lr"] *= 0.5
    else:
        task.log("train_loss", loss, prog_bar=True, on_step=False, on_epoch=True, batch_size=batch.samples)
    return loss


def log_loop_residual(task, batch: LoopBatch, name: str) -> torch.Tensor:
    """Log the closed-loop residual (nm²) of ``task``'s network over ``batch`` as ``name`` (a validation step)."""
    loss = batch_loss(task.network, task.spec, batch)
    task.log(name, loss, prog_bar=True, batch_size=batch.samples)
    return loss
