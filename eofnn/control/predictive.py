"""Runs any trained predictor in the closed loop, keeping its own history buffers."""

from __future__ import annotations

import torch
from torch import nn

from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.models.build import input_dtype
from eofnn.models.linear import LinearFilter
from eofnn.sim.loop import LoopInput


class HistoryRing:
    """The last ``length`` frames of a signal, most recent first, pushed without shifting the history.

    Frames are written at decreasing positions of a buffer ``spare`` slots longer than the history; the history
    is a view of ``length`` consecutive slots. Only when the buffer's start is reached are the newest frames
    copied back to its end, once every ``spare`` pushes.
    """

    def __init__(self, shape: tuple[int, ...], length: int, dtype: torch.dtype, spare: int = 256) -> None:
        self.length, self.spare = length, max(spare, length)
        self.buffer = torch.zeros(*shape, length + self.spare, dtype=dtype)
        self.pos = self.spare

    def push(self, frame: torch.Tensor) -> None:
        if self.pos == 0:
            keep = self.length - 1
            if keep:
                self.buffer[..., self.spare + 1: self.spare + 1 + keep] = self.buffer[..., :keep]
            self.pos = self.spare + 1
        self.pos -= 1
        self.buffer[..., self.pos] = frame

    @property
    def view(self) -> torch.Tensor:
        """``(..., length)`` history, most recent first."""
        return self.buffer[..., self.pos: self.pos + self.length]

    def __getitem__(self, lag: int) -> torch.Tensor:
        """The frame pushed ``lag`` pushes ago (0 is the newest)."""
        return self.buffer[..., self.pos + lag]


class PredictiveController:
    """Closed-loop controller around a predictor ``network`` that reads ``spec`` histories.

    Per frame it pushes the newest measurement into ring buffers (no recomputation or shifting of whole
    histories) and asks the network for ``y(n)``. Until the history is full (``spec.first_frame`` frames after a
    reset) the command is zero, so that every history the network sees is a true one (``eps = s + DM(y)`` with
    the commands really applied) rather than one padded with zeros.

    A per-actuator or shared :class:`~eofnn.models.linear.LinearFilter` whose weights live on the loop's device in
    the loop's dtype runs on a fast path: the history is written into one preallocated buffer and the filter is
    ``torch.mul`` and ``torch.sum`` into preallocated outputs, the same arithmetic as ``LinearFilter.forward``
    (bit-identical commands) without the per-step allocations.

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
        # Commands y(n-1), y(n-2), ...: the closed-loop taps and the POL reconstruction (y(n-d), and y(n-d-1)
        # for a fractional delay) read them.
        self._y = HistoryRing(shape, max(p, d + self.spec.target_lead), dtype)
        # Residuals (closed loop) or POL values (open loop) from frame n - d back.
        self._signal = HistoryRing(shape, p, dtype)
        self._frames_seen = 0
        self.network.eval()
        weight = getattr(self.network, "weight", None)
        fast = (isinstance(self.network, LinearFilter) and self.network.structure in ("per_actuator", "shared")
                and weight.dtype == dtype and weight.device == self._device == torch.device("cpu"))
        self._weight = weight.detach() if fast else None
        if fast:
            taps = self.spec.n_taps
            self._history = torch.empty(batch, n_actuators, taps, dtype=dtype)
            self._product = torch.empty(batch, n_actuators, taps, dtype=dtype)

    @torch.no_grad()
    def step(self, inp: LoopInput) -> torch.Tensor:
        p, d, f = self.spec.history_length, self.spec.whole_delay, self.spec.delay_fraction
        if self.spec.kind == "open_loop":
            applied = self._y[d - 1] if not f else (1 - f) * self._y[d - 1] + f * self._y[d]  # DM over frame n - d
            self._signal.push(inp.wfs - self.dm_gain_model * applied)  # POL value of frame n - d
        else:
            self._signal.push(inp.wfs)
        if self._frames_seen < self.spec.first_frame:
            y = torch.zeros_like(inp.wfs)
        elif self._weight is not None:
            y = self._fast_filter(p)
        else:
            if self.spec.kind == "open_loop":
                history = self._signal.view
            else:
                history = torch.cat([self._y.view[..., :p], self._signal.view], dim=-1)
            y = self.network(history.to(self._device, self._dtype)).to(inp.wfs.device, self._out_dtype)
        self._frames_seen += 1
        self._y.push(y)
        return y

    def _fast_filter(self, p: int) -> torch.Tensor:
        """``LinearFilter.forward`` of the current history, through the preallocated buffers."""
        if self.spec.kind == "open_loop":
            history = self._signal.view
        else:
            history = self._history
            history[..., :p].copy_(self._y.view[..., :p])
            history[..., p:].copy_(self._signal.view)
        torch.mul(history, self._weight, out=self._product)
        return self._product.sum(-1)
