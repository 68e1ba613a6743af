"""Non-stationary scenarios: the atmosphere and the DM change at given times (all off by default).

*Atmosphere changes* (``atmosphere.changes``, :class:`AtmosphereChange`): at ``at_s`` one layer's wind speed or
direction, or its strength, changes, at once or over ``ramp_s`` seconds.

- **Wind** (speed and/or direction). The layer models evaluate one frozen screen along one straight path (the
  ``exact`` model a periodic Fourier screen in the frame of its wind, with periods tied to the speed), so a new
  wind cannot follow the same screen. The layer is *cross-faded* to an independent screen of the same layer with the
  new wind: ``s = cos(pi/2 p) s_old + sin(pi/2 p) s_new`` with ``p`` rising from 0 at ``at_s`` to 1 at
  ``at_s + ramp_s`` as a smoothstep of time (:meth:`AtmosphereChange.progress`). The two screens are independent,
  so the weights keep the variance, the spatial covariance and the PSD exactly (``cos² + sin² = 1``) at every
  frame; what the fade does not keep is the temporal structure *during* the ramp: each frame-to-frame step gains
  up to ``1.5 (pi / 2) / ramp_frames`` of the layer's RMS from the weights' change (mid-ramp), in quadrature with
  the flow's own step (a 0.1 s ramp at 1 kHz: 2.4% of the RMS per frame, against 4.3% for the flow itself at
  5 m/s and 20 cm pitch, point kernel). With a *linear* ``p`` the weights' slope jumps at both ends of the ramp,
  which a predictor cannot extrapolate: every EOF's residual spiked there (``experiments/adaptive/wind_turn.yaml``;
  the numbers, with the smoothstep's: ``docs/findings.md``).
  ``ramp_s: 0`` switches from one frame to the next: a step of about sqrt(2) times the layer's RMS, which no
  predictor follows (a hard splice triggered the adaptive fallback in the earlier splice experiments). Frames
  after the ramp are the new screen alone, frozen flow with the new wind.
- **Strength** (``cn2_scale``): the layer's Cn² becomes ``cn2_scale`` times its configured ``cn2_fraction`` (its
  r0 scales by ``cn2_scale^(-3/5)``; other layers are untouched, so the total r0 changes). The same screen is
  scaled in amplitude by ``sqrt(c)``, ``c`` moving from its previous value to ``cn2_scale`` as ``p`` over the
  ramp: continuous, and the screen's shape is kept.

Each new screen of a layer has a seed of its own (the layer's seed key plus the change's index), it is built when a
frame first needs it (training sequences shorter than the change never build it) and it is evaluated at the
absolute frame number, so any frame range in any chunking gives the same numbers. Changes of one layer must not
overlap (the next starts at or after the previous ramp's end). Training data are simulated in the scenario as
given: every sequence starts at frame 0, so a change after ``data.sequence_frames`` frames is never seen by
training (a predictor is fitted for the conditions before the change).

*DM gain drift* (``plant.dm_gain_drift``, :class:`DmGainDrift`): the DM gain moves linearly from ``dm_gain`` at
``start_s`` to ``to`` at ``stop_s`` and then stays there. Only the simulated plant drifts: the analytic stability
analysis, the robustness maps' bounds and the controllers' pseudo-open-loop model use the static ``dm_gain``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from eofnn.errors import require
from eofnn.lazy import lazy_module
from eofnn.validation import Constraint, Interval, OrNone, from_mapping, validated

torch = lazy_module("torch")

#: Longest time a change or drift may name, in seconds (about 116 days).
MAX_TIME_S = 1e7


@dataclass(frozen=True)
@validated
class AtmosphereChange:
    """One change of one layer at a given time.

    Parameters
    ----------
    at_s : float
        Time the change starts, in seconds from frame 0.
    layer : int
        Index of the layer in ``atmosphere.layers``.
    ramp_s : float
        Duration of the change in seconds (0: from one frame to the next).
    wind_speed_mps, wind_direction_deg : float, optional
        The layer's new wind (m/s; degrees from +x towards +y); unset, the current one. Either makes this a wind
        change: a cross-fade to an independent screen with that wind (module docstring).
    cn2_scale : float, optional
        The layer's Cn² after the change, relative to its configured ``cn2_fraction`` (1 restores it).
    """

    at_s: float
    layer: int = 0
    ramp_s: float = 0.0
    wind_speed_mps: float | None = None
    wind_direction_deg: float | None = None
    cn2_scale: float | None = None

    _constraints: ClassVar[dict[str, Constraint]] = {
        "at_s": Interval(0, MAX_TIME_S, unit="s"),
        "layer": Interval(0, 1000, integer=True),
        "ramp_s": Interval(0, MAX_TIME_S, unit="s"),
        "wind_speed_mps": OrNone(Interval(0, 1000, unit="m/s")),
        "wind_direction_deg": OrNone(Interval(-360, 360, unit="degrees")),
        "cn2_scale": OrNone(Interval(0, 1e6, closed="right")),
    }
    _where: ClassVar[str] = "atmosphere.changes: "

    def __post_init__(self) -> None:
        require(self.changes_wind or self.cn2_scale is not None,
                f"atmosphere.changes: the change at at_s={self.at_s!r} changes nothing: give wind_speed_mps, "
                "wind_direction_deg or cn2_scale")

    @property
    def changes_wind(self) -> bool:
        """Whether this change gives the layer a new wind (an independent screen)."""
        return self.wind_speed_mps is not None or self.wind_direction_deg is not None

    def progress(self, frames: torch.Tensor, frame_rate_hz: float) -> torch.Tensor:
        """Fraction ``p`` of the change done at each frame of ``frames``: 0 before ``at_s``, 1 after the ramp, and
        ``3 u² - 2 u³`` of the ramp's time fraction ``u`` in between (smoothstep: no kink at either end)."""
        t = frames.to(torch.float64) / frame_rate_hz
        if self.ramp_s == 0:
            return (t >= self.at_s).to(torch.float64)
        u = ((t - self.at_s) / self.ramp_s).clamp(0.0, 1.0)
        return u * u * (3 - 2 * u)


def _require_start(change: dict) -> None:
    require("at_s" in change, f"atmosphere.changes: {change!r} has no at_s (the time it starts, s)")


def build_changes(changes: Any, layers: Sequence[Any]) -> list[AtmosphereChange]:
    """``atmosphere.changes`` as a list of :class:`AtmosphereChange`, sorted by time, checked against ``layers``."""
    require(isinstance(changes, (list, tuple)),
            f"atmosphere.changes={changes!r} is invalid: give a list of changes, e.g. [{{at_s: 5.0, layer: 0, "
            "wind_speed_mps: 20.0}]")
    out = []
    for change in changes:
        if isinstance(change, dict):
            change = from_mapping(AtmosphereChange, change, "atmosphere.changes", sort_allowed=False,
                                  check_keys=_require_start)
        require(isinstance(change, AtmosphereChange), f"atmosphere.changes: {change!r} is invalid: give a mapping")
        require(change.layer < len(layers), f"atmosphere.changes: layer={change.layer} is invalid: the atmosphere has "
                                            f"{len(layers)} layer(s) (indices from 0)")
        out.append(change)
    out.sort(key=lambda c: c.at_s)
    for i, change in enumerate(out):
        later = [c for c in out[i + 1:] if c.layer == change.layer]
        if later:
            require(later[0].at_s >= change.at_s + change.ramp_s,
                    f"atmosphere.changes: the changes of layer {change.layer} at {change.at_s:g} s (ramp "
                    f"{change.ramp_s:g} s) and {later[0].at_s:g} s overlap: start the next after the ramp ends")
    return out


def layer_winds(layer: Any, changes: Sequence[AtmosphereChange]) -> list[Any]:
    """The layer as it is after each of its wind changes (``changes`` of this layer, in time order)."""
    out, current = [], layer
    for change in changes:
        if change.changes_wind:
            current = dataclasses.replace(
                current,
                wind_speed_mps=current.wind_speed_mps if change.wind_speed_mps is None else change.wind_speed_mps,
                wind_direction_deg=(current.wind_direction_deg if change.wind_direction_deg is None
                                    else change.wind_direction_deg))
            out.append(current)
    return out


def strongest_cn2_scale(layers: Sequence[Any], changes: Sequence[AtmosphereChange]) -> float:
    """The largest total Cn² over a run relative to the configured one, ``max_t sum_i f_i c_i(t) / sum_i f_i``
    (``f_i`` the layers' ``cn2_fraction``, ``c_i(t)`` their ``cn2_scale`` at ``t``): r0 is smallest, by that to the
    power ``-3/5``, when it peaks. A ramp moves each scale monotonically between two values, so the peak is at a time
    every ramp has ended or not begun: the start and the end of each ramp."""
    total = sum(lay.cn2_fraction for lay in layers)
    times = sorted({0.0} | {c.at_s + c.ramp_s for c in changes})

    def scale(index: int, t: float) -> float:
        done = [c.cn2_scale for c in changes if c.layer == index and c.cn2_scale is not None and c.at_s + c.ramp_s <= t]
        return done[-1] if done else 1.0

    return max(sum(lay.cn2_fraction * scale(i, t) for i, lay in enumerate(layers)) for t in times) / total


class ChangingLayer:
    """One realisation of one layer whose wind and strength change (:class:`AtmosphereChange`).

    Serves frames like the layer generators (``frames(start, stop, basis)`` and ``write_frames``).

    Parameters
    ----------
    first : object
        The layer's generator before any wind change (the stationary layer's, same seed).
    layer : Layer
        The layer's configuration.
    changes : sequence of AtmosphereChange
        This layer's changes, in time order, not overlapping.
    frame_rate_hz : float
        Frames per second.
    make_screen : callable
        ``make_screen(layer, index)``: an independent generator of ``layer`` (with its new wind) for wind change
        ``index`` (1, 2, ...), seeded from that index.
    """

    def __init__(self, first: Any, layer: Any, changes: Sequence[AtmosphereChange], frame_rate_hz: float,
                 make_screen: Callable[[Any, int], Any]) -> None:
        self.frame_rate_hz = frame_rate_hz
        self._changes = list(changes)
        self._wind_changes = [c for c in self._changes if c.changes_wind]
        self._winds = layer_winds(layer, self._changes)
        self._screens: list[Any] = [first] + [None] * len(self._wind_changes)
        self._make_screen = make_screen

    def _screen(self, k: int) -> Any:
        if self._screens[k] is None:
            self._screens[k] = self._make_screen(self._winds[k - 1], k)
        return self._screens[k]

    def screen_weights(self, frames: torch.Tensor) -> list[torch.Tensor]:
        """Weight of each screen at ``frames`` (at most two non-zero; their squares add to one)."""
        done = [torch.ones_like(frames, dtype=torch.float64)]
        done += [c.progress(frames, self.frame_rate_hz) for c in self._wind_changes]
        done.append(torch.zeros_like(frames, dtype=torch.float64))
        # Exact zeros before a screen fades in and after it has faded out (cos(pi/2) is 6e-17 in floating point).
        return [torch.where((done[k] > 0) & (done[k + 1] < 1),
                            torch.sin(math.pi / 2 * done[k]) * torch.cos(math.pi / 2 * done[k + 1]), 0.0)
                for k in range(len(self._screens))]

    def amplitude(self, frames: torch.Tensor) -> torch.Tensor:
        """Amplitude factor ``sqrt(c)`` of the layer at ``frames`` (``c``: its Cn² relative to the configured)."""
        scale = torch.ones_like(frames, dtype=torch.float64)
        for change in self._changes:
            if change.cn2_scale is not None:
                scale = scale + (change.cn2_scale - scale) * change.progress(frames, self.frame_rate_hz)
        return scale.sqrt()

    def frames(self, start: int, stop: int, basis: torch.Tensor | None = None) -> torch.Tensor:
        """OPD (nm) of frames ``start..stop-1``, ``(frames, n_actuators)``; ``basis`` projected out."""
        n = torch.arange(start, stop)
        amplitude = self.amplitude(n)
        out = None
        for k, weight in enumerate(self.screen_weights(n)):
            active = torch.nonzero(weight).flatten()
            if len(active) == 0:
                continue
            lo, hi = int(active[0]), int(active[-1]) + 1
            part = self._screen(k).frames(start + lo, start + hi, basis) * (weight[lo:hi] * amplitude[lo:hi])[:, None]
            if out is None:
                out = torch.zeros(stop - start, part.shape[1], dtype=torch.float64)
            out[lo:hi] += part
        require(out is not None, f"no screen covers frames [{start}, {stop})")
        return out

    def write_frames(self, start: int, stop: int, out: torch.Tensor, add: bool = False) -> torch.Tensor:
        """Write (or, with ``add``, add) the OPD (nm) of frames ``start..stop-1`` into ``out``."""
        frames = self.frames(start, stop)
        return out.add_(frames) if add else out.copy_(frames)


def with_changes(first: Any, layer: Any, index: int, changes: Sequence[AtmosphereChange], frame_rate_hz: float,
                 make_screen: Callable[[Any, int], Any]) -> Any:
    """``first`` itself if layer ``index`` has no change (the stationary layer, bit for bit), else a
    :class:`ChangingLayer`."""
    own = [c for c in changes if c.layer == index]
    return ChangingLayer(first, layer, own, frame_rate_hz, make_screen) if own else first


@dataclass(frozen=True)
@validated
class DmGainDrift:
    """The DM gain moving linearly from the plant's ``dm_gain`` at ``start_s`` to ``to`` at ``stop_s``, then held.

    Only the simulated DM drifts: the analytic stability and the robustness bounds, and the controllers' model of
    the DM, use the static ``dm_gain``.

    Parameters
    ----------
    start_s, stop_s : float
        Start and end of the drift, in seconds from frame 0 (equal: a step at ``start_s``).
    to : float
        DM gain at and after ``stop_s``.
    """

    start_s: float
    stop_s: float
    to: float

    _constraints: ClassVar[dict[str, Constraint]] = {
        "start_s": Interval(0, MAX_TIME_S, unit="s"),
        "stop_s": Interval(0, MAX_TIME_S, unit="s"),
        "to": Interval(0, 100, closed="right"),
    }
    _where: ClassVar[str] = "plant.dm_gain_drift."

    def __post_init__(self) -> None:
        require(self.stop_s >= self.start_s, f"plant.dm_gain_drift.stop_s={self.stop_s!r} is invalid: it must be at "
                                             f"least start_s={self.start_s!r}")

    def gain(self, time_s: float, dm_gain: float) -> float:
        """DM gain at ``time_s`` for a drift starting from ``dm_gain``."""
        if time_s <= self.start_s:
            return dm_gain
        if time_s >= self.stop_s:
            return self.to
        return dm_gain + (self.to - dm_gain) * (time_s - self.start_s) / (self.stop_s - self.start_s)


def build_drift(drift: Any) -> DmGainDrift | None:
    """``plant.dm_gain_drift`` as a :class:`DmGainDrift` (``None`` stays ``None``: no drift)."""
    if drift is None or isinstance(drift, DmGainDrift):
        return drift
    require(isinstance(drift, dict), f"plant.dm_gain_drift={drift!r} is invalid: give {{start_s, stop_s, to}}")
    return from_mapping(DmGainDrift, drift, "plant.dm_gain_drift", sort_allowed=False, check_keys=_require_drift_keys)


def _require_drift_keys(drift: dict) -> None:
    missing = [f.name for f in dataclasses.fields(DmGainDrift) if f.name not in drift]
    require(not missing, f"plant.dm_gain_drift={drift!r} is invalid: it needs {', '.join(missing)}")
