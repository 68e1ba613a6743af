"""History tensors: telemetry -> ``(samples, actuators, taps)`` regressors and their targets.

The same functions serve training, evaluation and real telemetry. Taps run from the most recent to the oldest.

- open loop: ``[s_hat(n-d), ..., s_hat(n-d-p+1)]`` with the pseudo-open-loop value ``s_hat = wfs - g_model * y``;
- closed loop: ``[y(n-1), ..., y(n-p), eps(n-d), ..., eps(n-d-p+1)]`` (``eps`` as the WFS reported it);
- target: the command that cancels the turbulence, ``-s(n) / g``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import ClassVar, Literal

import torch

from eofnn.errors import ConfigError
from eofnn.sim.scenario import Scenario
from eofnn.validation import Constraint, Interval, OneOf, validated

HISTORY_KINDS = ("open_loop", "closed_loop")
#: Longest history accepted (frames); a 1264-actuator closed-loop history of this length is ~1 MB per frame.
MAX_HISTORY_LENGTH = 256


@dataclass(frozen=True)
@validated
class HistorySpec:
    """What a predictor sees: the kind of history, how many frames of it, and the loop delay.

    Parameters
    ----------
    kind : {"open_loop", "closed_loop"}
        Pseudo-open-loop values, or past commands and residuals.
    history_length : int
        Frames of history ``p`` (taps per signal).
    delay_frames : int
        Loop delay ``d``: the newest residual available for ``y(n)`` is ``eps(n - d)``.
    """

    kind: Literal["open_loop", "closed_loop"] = "open_loop"
    history_length: int = 4
    delay_frames: int = 2

    _constraints: ClassVar[dict[str, Constraint]] = {
        "kind": OneOf(HISTORY_KINDS),
        "history_length": Interval(1, MAX_HISTORY_LENGTH, integer=True, unit="frames"),
        "delay_frames": Interval(1, 100, integer=True, unit="frames"),
    }

    @classmethod
    def from_scenario(cls, kind: str, history_length: int, scenario: Scenario) -> HistorySpec:
        """The history a predictor of ``kind`` and ``history_length`` reads in ``scenario`` (its plant's delay)."""
        return cls(kind, history_length, scenario.plant.delay_frames)

    @property
    def n_taps(self) -> int:
        """Taps per actuator in the history tensor."""
        return self.history_length * (2 if self.kind == "closed_loop" else 1)

    @property
    def first_frame(self) -> int:
        """First frame ``n`` whose history lies entirely inside the telemetry."""
        oldest = self.delay_frames + self.history_length - 1
        return max(oldest, self.history_length) if self.kind == "closed_loop" else oldest

    def to_dict(self) -> dict:
        return asdict(self)


def _lagged(x: torch.Tensor, lags: range, first: int) -> torch.Tensor:
    """Stack ``x[..., n - lag, :]`` for ``n >= first`` and each lag into ``(..., samples, K, len(lags))``."""
    t = x.shape[-2]
    return torch.stack([x[..., first - lag: t - lag, :] for lag in lags], dim=-1)


def pseudo_open_loop(wfs: torch.Tensor, y: torch.Tensor, dm_gain_model: float = 1.0) -> torch.Tensor:
    """POL reconstruction ``s_hat = wfs - g_model * y``: exact only if the DM applies ``g_model * y``."""
    return wfs - dm_gain_model * y


def open_loop_history(s_hat: torch.Tensor, spec: HistorySpec) -> torch.Tensor:
    """``(..., samples, K, p)`` history of POL values for frames ``n >= spec.first_frame``."""
    d, p = spec.delay_frames, spec.history_length
    return _lagged(s_hat, range(d, d + p), spec.first_frame)


def closed_loop_history(y: torch.Tensor, eps: torch.Tensor, spec: HistorySpec) -> torch.Tensor:
    """``(..., samples, K, 2p)`` history of commands then residuals for frames ``n >= spec.first_frame``."""
    d, p, first = spec.delay_frames, spec.history_length, spec.first_frame
    return torch.cat([_lagged(y, range(1, p + 1), first), _lagged(eps, range(d, d + p), first)], dim=-1)


def build_history(spec: HistorySpec, *, s: torch.Tensor | None = None, y: torch.Tensor | None = None,
                  wfs: torch.Tensor | None = None, dm_gain_model: float = 1.0) -> torch.Tensor:
    """History tensor for ``spec`` from telemetry arrays ``(..., frames, K)``.

    Open loop uses ``wfs`` and ``y`` (POL) or, with neither given, the turbulence ``s`` itself (perfect POL).
    """
    if spec.kind == "open_loop":
        s_hat = s if wfs is None else pseudo_open_loop(wfs, y, dm_gain_model)
        if s_hat is None:
            raise ConfigError("open-loop history needs s, or wfs and y")
        return open_loop_history(s_hat, spec)
    if y is None or wfs is None:
        raise ConfigError("closed-loop history needs y and wfs")
    return closed_loop_history(y, wfs, spec)


def targets(s: torch.Tensor, spec: HistorySpec, dm_gain: float = 1.0) -> torch.Tensor:
    """``(..., samples, K)`` commands that cancel the turbulence, ``-s(n) / dm_gain``, for ``n >= first_frame``."""
    return -s[..., spec.first_frame:, :] / dm_gain
