"""History tensors: telemetry -> ``(samples, actuators, taps)`` regressors and their targets.

The same functions serve training, evaluation and real telemetry. Taps run from the most recent to the oldest.

- open loop: ``[s_hat(n-d), ..., s_hat(n-d-p+1)]`` with the pseudo-open-loop value ``s_hat = wfs - g_model * y``;
- closed loop: ``[y(n-1), ..., y(n-p), eps(n-d), ..., eps(n-d-p+1)]`` (``eps`` as the WFS reported it);
- target: the command that cancels the turbulence, ``-s(n) / g``.

A fractional delay ``d + f`` (:mod:`eofnn.delay`) keeps the taps (``d`` is the whole part) and changes what
the DM applied: the POL value is ``s_hat(n) = wfs(n) - g_model ((1 - f) y(n) + f y(n-1))``, and since ``y(n)``
acts over frame ``n`` with weight ``1 - f`` and over frame ``n + 1`` with weight ``f``, its target is the command
that cancels the turbulence averaged over those frames, ``-((1 - f) s(n) + f s(n+1)) / g`` (to first order in the
turbulence's change per frame, the residual of the averaged DM shape then vanishes; the last frame of a sequence
has no target).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import ClassVar, Literal

from eofnn.delay import DELAY, check_delay, split_delay
from eofnn.errors import ConfigError
from eofnn.lazy import lazy_module
from eofnn.sim.scenario import Scenario
from eofnn.validation import Constraint, Interval, OneOf, validated

torch = lazy_module("torch")

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
    delay_frames : int or float
        Loop delay ``tau = d + f``: the newest residual available for ``y(n)`` is ``eps(n - d)``; a fraction ``f``
        of each frame still sees the previous command (see the module docstring).
    """

    kind: Literal["open_loop", "closed_loop"] = "open_loop"
    history_length: int = 4
    delay_frames: int | float = 2

    _constraints: ClassVar[dict[str, Constraint]] = {
        "kind": OneOf(HISTORY_KINDS),
        "history_length": Interval(1, MAX_HISTORY_LENGTH, integer=True, unit="frames"),
        "delay_frames": DELAY,
    }

    def __post_init__(self) -> None:
        object.__setattr__(self, "delay_frames", check_delay(self.delay_frames))  # 2.0 -> 2: integers stay ints

    @classmethod
    def from_scenario(cls, kind: str, history_length: int, scenario: Scenario) -> HistorySpec:
        """The history a predictor of ``kind`` and ``history_length`` reads in ``scenario`` (its plant's delay)."""
        return cls(kind, history_length, scenario.plant.delay_frames)

    @property
    def n_taps(self) -> int:
        """Taps per actuator in the history tensor."""
        return self.history_length * (2 if self.kind == "closed_loop" else 1)

    @property
    def whole_delay(self) -> int:
        """``d = floor(delay_frames)``: the lag of the newest residual."""
        return split_delay(self.delay_frames)[0]

    @property
    def delay_fraction(self) -> float:
        """``f = delay_frames - d``: the weight of the previous command in the DM shape of a frame."""
        return split_delay(self.delay_frames)[1]

    @property
    def target_lead(self) -> int:
        """Frames after ``n`` that the target of frame ``n`` needs: 1 for a fractional delay, else 0."""
        return 1 if self.delay_fraction else 0

    @property
    def first_frame(self) -> int:
        """First frame ``n`` whose history lies entirely inside the telemetry."""
        oldest = self.whole_delay + self.history_length - 1
        if self.kind == "closed_loop":
            return max(oldest, self.history_length)
        return oldest + self.target_lead  # a fractional POL value also reads the command one frame earlier

    def to_dict(self) -> dict:
        return asdict(self)


def _lagged(x: torch.Tensor, lags: range, first: int, lead: int = 0) -> torch.Tensor:
    """Stack ``x[..., n - lag, :]`` for ``first <= n < frames - lead`` and each lag into ``(..., samples, K, lags)``."""
    t = x.shape[-2] - lead
    return torch.stack([x[..., first - lag: t - lag, :] for lag in lags], dim=-1)


def applied_command(y: torch.Tensor, delay_fraction: float) -> torch.Tensor:
    """The command acting over each frame, ``(1 - f) y(n) + f y(n-1)`` (``y(-1) = 0``), ``(..., frames, K)``."""
    if not delay_fraction:
        return y
    previous = torch.cat([torch.zeros_like(y[..., :1, :]), y[..., :-1, :]], dim=-2)
    return (1 - delay_fraction) * y + delay_fraction * previous


def pseudo_open_loop(wfs: torch.Tensor, y: torch.Tensor, dm_gain_model: float = 1.0,
                     delay_fraction: float = 0.0) -> torch.Tensor:
    """POL reconstruction ``s_hat = wfs - g_model * y_applied``: exact only if the DM applies ``g_model * y``.

    ``y_applied`` is :func:`applied_command` (``y`` itself for an integer delay).
    """
    return wfs - dm_gain_model * applied_command(y, delay_fraction)


def open_loop_history(s_hat: torch.Tensor, spec: HistorySpec) -> torch.Tensor:
    """``(..., samples, K, p)`` history of POL values for frames ``first_frame <= n < frames - target_lead``."""
    d, p = spec.whole_delay, spec.history_length
    return _lagged(s_hat, range(d, d + p), spec.first_frame, spec.target_lead)


def closed_loop_history(y: torch.Tensor, eps: torch.Tensor, spec: HistorySpec) -> torch.Tensor:
    """``(..., samples, K, 2p)`` history of commands then residuals for ``first_frame <= n < frames - target_lead``."""
    d, p, first, lead = spec.whole_delay, spec.history_length, spec.first_frame, spec.target_lead
    return torch.cat([_lagged(y, range(1, p + 1), first, lead), _lagged(eps, range(d, d + p), first, lead)], dim=-1)


def build_history(spec: HistorySpec, *, s: torch.Tensor | None = None, y: torch.Tensor | None = None,
                  wfs: torch.Tensor | None = None, dm_gain_model: float = 1.0) -> torch.Tensor:
    """History tensor for ``spec`` from telemetry arrays ``(..., frames, K)``.

    Open loop uses ``wfs`` and ``y`` (POL) or, with neither given, the turbulence ``s`` itself (perfect POL).
    """
    if spec.kind == "open_loop":
        s_hat = s if wfs is None else pseudo_open_loop(wfs, y, dm_gain_model, spec.delay_fraction)
        if s_hat is None:
            raise ConfigError("open-loop history needs s, or wfs and y")
        return open_loop_history(s_hat, spec)
    if y is None or wfs is None:
        raise ConfigError("closed-loop history needs y and wfs")
    return closed_loop_history(y, wfs, spec)


def blended_target(s: torch.Tensor, spec: HistorySpec) -> torch.Tensor:
    """``(..., samples, K)`` turbulence each command must cancel: ``s(n)``, or ``(1 - f) s(n) + f s(n+1)`` for a
    fractional delay, for ``first_frame <= n < frames - target_lead`` (the module docstring says why)."""
    first, f = spec.first_frame, spec.delay_fraction
    if not f:
        return s[..., first:, :]
    return (1 - f) * s[..., first:-1, :] + f * s[..., first + 1:, :]


def targets(s: torch.Tensor, spec: HistorySpec, dm_gain: float = 1.0) -> torch.Tensor:
    """``(..., samples, K)`` commands that cancel the turbulence, ``-s(n) / dm_gain`` (for a fractional delay
    its average over the frames the command acts on, :func:`blended_target`), for ``n >= first_frame``."""
    return -blended_target(s, spec) / dm_gain
