"""Runs any trained predictor in the closed loop, keeping its own history buffers."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.models.build import input_dtype
from eofnn.models.linear import LinearFilter
from eofnn.sim.loop.runner import LoopInput


class HistoryRing:
    """The last ``length`` frames of a signal, most recent first, pushed without shifting the history.

    Frames are written at decreasing positions of a buffer ``spare`` slots longer than the history; the history
    is a view of ``length`` consecutive slots. Only when the buffer's start is reached are the newest frames
    copied back to its end, once every ``spare`` pushes. The views of every position are made once, so a push or
    a read is a list lookup rather than a tensor indexing call.
    """

    def __init__(self, shape: tuple[int, ...], length: int, dtype: torch.dtype, spare: int = 256) -> None:
        self.length, self.spare = length, max(spare, length)
        self.buffer = torch.zeros(*shape, length + self.spare, dtype=dtype)
        self.pos = self.spare
        self._slots = self.buffer.unbind(-1)
        self._views = [self.buffer[..., i: i + length] for i in range(self.spare + 1)]

    def next_slot(self) -> torch.Tensor:
        """Make room for a new frame and return its slot, ``(...)``: writing into it pushes the frame."""
        if self.pos == 0:
            keep = self.length - 1
            if keep:
                self.buffer[..., self.spare + 1: self.spare + 1 + keep] = self.buffer[..., :keep]
            self.pos = self.spare + 1
        self.pos -= 1
        return self._slots[self.pos]

    def push(self, frame: torch.Tensor) -> None:
        self.next_slot().copy_(frame)

    @property
    def view(self) -> torch.Tensor:
        """``(..., length)`` history, most recent first."""
        return self._views[self.pos]

    def __getitem__(self, lag: int) -> torch.Tensor:
        """The frame pushed ``lag`` pushes ago (0 is the newest)."""
        return self._slots[self.pos + lag]


class LinearFilterStep:
    """The controller step of a per-actuator or shared :class:`~eofnn.models.linear.LinearFilter`, on buffers
    allocated once: two small writes, one ``torch.mul`` and one ``torch.sum`` per step.

    The arithmetic is ``LinearFilter.forward``'s (the same products summed by the same reduction over a contiguous
    ``(batch, K, taps)`` block), so the commands are bit-identical to the general path's. What it saves is the
    traffic around it: the closed-loop commands and residuals share one ring (``(batch, K, 2, p + spare)``: row 0
    ``y(n-1), y(n-2), ...``, row 1 ``eps(n-d), ...`` at the same positions), so the filter reads the two histories
    in place instead of concatenating them; the open-loop pseudo-open-loop value is computed straight into its ring
    slot; past commands for it sit in a ``(d, batch, K)`` ring indexed by frame.

    Parameters
    ----------
    weight : Tensor
        The filter's ``(K, taps)`` or ``(1, taps)`` weights (detached), in ``dtype`` on the CPU.
    spec : HistorySpec
        The history the filter reads.
    dm_gain_model : float
        DM gain of the pseudo-open-loop reconstruction (open loop only).
    batch, n_actuators : int
        Loop shape.
    dtype : torch.dtype
        The loop's dtype.
    spare : int
        Extra ring slots (:class:`HistoryRing`): the newest frames are copied back once every ``spare`` steps.
    """

    def __init__(self, weight: torch.Tensor, spec: HistorySpec, dm_gain_model: float, batch: int,
                 n_actuators: int, dtype: torch.dtype, spare: int = 256) -> None:
        self.spec, self.dm_gain_model = spec, dm_gain_model
        p, d = spec.history_length, spec.whole_delay
        self._closed = spec.kind == "closed_loop"
        self._products = torch.empty(batch, n_actuators, spec.n_taps, dtype=dtype)
        if self._closed:
            self._ring = HistoryRing((batch, n_actuators, 2), p, dtype, spare)
            self._weight = weight.view(weight.shape[0], 2, p)
            self._products_out = self._products.view(batch, n_actuators, 2, p)
            slots = self._ring.buffer.unbind(-1)
            self._y_slots, self._eps_slots = [s[..., 0] for s in slots], [s[..., 1] for s in slots]
        else:
            self._ring = HistoryRing((batch, n_actuators), p, dtype, spare)
            self._weight = weight
            self._products_out = self._products
            self._y_past = torch.zeros(d, batch, n_actuators, dtype=dtype).unbind(0)  # slot n % d: y(n-d), then y(n)
            self._scaled = torch.empty(batch, n_actuators, dtype=dtype)

    def step(self, wfs: torch.Tensor, frame: int, active: bool) -> torch.Tensor:
        """``y(n)`` for the measurement ``wfs`` of frame ``frame`` after the reset; zeros unless ``active``."""
        ring = self._ring
        if self._closed:
            self._eps_slots[ring.pos].copy_(wfs)  # eps(n - d) beside y(n - 1), written at the end of the last step
        else:
            y_past = self._y_past[frame % self.spec.whole_delay]
            self._pseudo_open_loop(ring.next_slot(), wfs, y_past)
        if active:
            torch.mul(ring.view, self._weight, out=self._products_out)
            y = self._products.sum(-1)
        else:
            y = torch.zeros_like(wfs)
        if self._closed:
            ring.next_slot()
            self._y_slots[ring.pos].copy_(y)
        else:
            y_past.copy_(y)
        return y

    def applied(self, command: torch.Tensor, frame: int) -> None:
        """The command really applied for ``frame`` (the last step's) replaces the filter's own in its histories."""
        if self._closed:
            self._y_slots[self._ring.pos].copy_(command)
        else:
            self._y_past[frame % self.spec.whole_delay].copy_(command)

    def _pseudo_open_loop(self, out: torch.Tensor, wfs: torch.Tensor, y_old: torch.Tensor) -> None:
        """``out = wfs - dm_gain_model * y(n - d)``, the POL value of frame ``n - d``, rounded as the general path."""
        if self.dm_gain_model == 1.0:
            torch.sub(wfs, y_old, out=out)
        else:
            torch.mul(y_old, self.dm_gain_model, out=self._scaled)
            torch.sub(wfs, self._scaled, out=out)


def believed_dm_gain(configured: float | None = None, predictor: Any = None) -> float:
    """The DM gain a predictive controller believes (its pseudo-open-loop reconstruction): the one ``configured`` when
    set, else the ``predictor``'s own model (``dm_gain_model``: identified or given when it learnt from telemetry),
    else 1 (the nominal DM)."""
    if configured is None:
        configured = getattr(predictor, "dm_gain_model", 1.0) if predictor is not None else 1.0
    return float(configured)


class PredictiveController:
    """Closed-loop controller around a predictor ``network`` that reads ``spec`` histories.

    Per frame it pushes the newest measurement into ring buffers (no recomputation or shifting of whole
    histories) and asks the network for ``y(n)``. Until the history is full (``spec.first_frame`` frames after a
    reset) the command is zero, so that every history the network sees is a true one (``eps = s + DM(y)`` with
    the commands really applied) rather than one padded with zeros.

    A per-actuator or shared :class:`~eofnn.models.linear.LinearFilter` whose weights live on the CPU in the
    loop's dtype runs on :class:`LinearFilterStep` (bit-identical commands, fewer passes over the history).

    Parameters
    ----------
    network : nn.Module
        Maps ``(batch, K, spec.n_taps)`` histories to ``(batch, K)`` commands in nm.
    spec : HistorySpec
        The history the network was trained on.
    dm_gain_model : float
        DM gain the controller believes, used for the pseudo-open-loop reconstruction (open loop only).
    """

    def __init__(self, network: nn.Module, spec: HistorySpec, dm_gain_model: float = 1.0) -> None:
        self.network, self.spec, self.dm_gain_model = network, spec, dm_gain_model
        params = list(network.parameters())
        self._dtype = input_dtype(network)
        # The loop runs where the turbulence is (CPU); a network on another device gets its input moved there.
        self._device = params[0].device if params else torch.device("cpu")

    def reset(self, batch: int, n_actuators: int, delay_frames: int | float, dtype: torch.dtype) -> None:
        if delay_frames != self.spec.delay_frames:
            raise ConfigError(f"predictor was trained for delay_frames={self.spec.delay_frames} but the plant has "
                              f"delay_frames={delay_frames}")
        p, d = self.spec.history_length, self.spec.whole_delay
        shape = (batch, n_actuators)
        self._out_dtype = dtype
        self._frames_seen = 0
        self.network.eval()
        weight = getattr(self.network, "weight", None)
        # The fast path's pseudo-open-loop ring holds y(n - d) only: a fractional delay also needs y(n - d - 1).
        fast = (isinstance(self.network, LinearFilter) and self.network.structure in ("per_actuator", "shared")
                and weight.dtype == dtype and weight.device == self._device == torch.device("cpu")
                and (self.spec.kind == "closed_loop" or not self.spec.delay_fraction))
        self._fast = (LinearFilterStep(weight.detach(), self.spec, self.dm_gain_model, batch, n_actuators, dtype)
                      if fast else None)
        if not fast:
            # Commands y(n-1), y(n-2), ...: the closed-loop taps and the POL reconstruction (y(n-d), and y(n-d-1)
            # for a fractional delay) read them.
            self._y = HistoryRing(shape, max(p, d + self.spec.target_lead), dtype)
            # Residuals (closed loop) or POL values (open loop) from frame n - d back.
            self._signal = HistoryRing(shape, p, dtype)

    def step(self, inp: LoopInput) -> torch.Tensor:
        n = self._frames_seen
        self._frames_seen = n + 1
        if self._fast is not None:
            return self._fast.step(inp.wfs, n, n >= self.spec.first_frame)
        return self._general_step(inp.wfs, n >= self.spec.first_frame)

    def applied(self, command: torch.Tensor) -> None:
        """The command the loop really applied for the last step's frame, when it is not this controller's own (a
        composite that runs this predictor on some modes only, :class:`eofnn.control.fallback.ModalFallback`): the
        closed-loop taps and the pseudo-open-loop reconstruction read it from now on, as they read telemetry."""
        if self._fast is not None:
            self._fast.applied(command, self._frames_seen - 1)
        else:
            self._y[0].copy_(command)

    @torch.no_grad()
    def _general_step(self, wfs: torch.Tensor, active: bool) -> torch.Tensor:
        p, d, f = self.spec.history_length, self.spec.whole_delay, self.spec.delay_fraction
        if self.spec.kind == "open_loop":
            applied = self._y[d - 1] if not f else (1 - f) * self._y[d - 1] + f * self._y[d]  # DM over frame n - d
            self._signal.push(wfs - self.dm_gain_model * applied)  # POL value of frame n - d
        else:
            self._signal.push(wfs)
        if not active:
            y = torch.zeros_like(wfs)
        else:
            if self.spec.kind == "open_loop":
                history = self._signal.view
            else:
                history = torch.cat([self._y.view[..., :p], self._signal.view], dim=-1)
            y = self.network(history.to(self._device, self._dtype)).to(wfs.device, self._out_dtype)
        self._y.push(y)
        return y
