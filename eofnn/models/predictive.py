"""Runs any trained predictor in the closed loop, keeping its own history buffers."""

from __future__ import annotations

import torch
from torch import nn

from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.sim.loop import LoopInput


class PredictiveController:
    """Closed-loop controller around a predictor ``network`` that reads ``spec`` histories.

    Per frame it pushes the newest measurement into a ring of histories (no recomputation of whole histories)
    and asks the network for ``y(n)``. Until the history is full (``spec.first_frame`` frames after a reset) the
    command is zero, so that every history the network sees is a true one (``eps = s + DM(y)`` with the commands
    really applied) rather than one padded with zeros.

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
        self._dtype = params[0].dtype if params else torch.float64

    def reset(self, batch: int, n_actuators: int, delay_frames: int, dtype: torch.dtype) -> None:
        if delay_frames != self.spec.delay_frames:
            raise ConfigError(f"predictor was trained for delay_frames={self.spec.delay_frames} but the plant has "
                              f"delay_frames={delay_frames}")
        p, d = self.spec.history_length, self.spec.delay_frames
        self._out_dtype = dtype
        self._history = torch.zeros(batch, n_actuators, self.spec.n_taps, dtype=dtype)
        # Commands y(n-1), ..., y(n-max(p, d)): the closed-loop taps and the POL reconstruction both need them.
        self._y = torch.zeros(batch, n_actuators, max(p, d), dtype=dtype)
        self._frames_seen = 0
        self.network.eval()

    @torch.no_grad()
    def step(self, inp: LoopInput) -> torch.Tensor:
        p, d = self.spec.history_length, self.spec.delay_frames
        h = self._history
        if self.spec.kind == "open_loop":
            s_hat = inp.wfs - self.dm_gain_model * self._y[..., d - 1]  # POL value of frame n - d
            h[..., 1:] = h[..., :-1].clone()
            h[..., 0] = s_hat
        else:
            h[..., p + 1:] = h[..., p:-1].clone()
            h[..., p] = inp.wfs
            h[..., :p] = self._y[..., :p]
        if self._frames_seen < self.spec.first_frame:
            y = torch.zeros_like(inp.wfs)
        else:
            y = self.network(h.to(self._dtype)).to(self._out_dtype)
        self._frames_seen += 1
        self._y[..., 1:] = self._y[..., :-1].clone()
        self._y[..., 0] = y
        return y
