"""The AO plant: loop delay, the deformable mirror as it really responds, and the wavefront sensor.

The controller believes the DM applies its command ``y`` exactly; the plant may disagree (the *model errors*,
each off by default): a gain ``dm_gain`` (the DM applies ``g * y``), a misregistration (the applied shape is
shifted by a fraction of an actuator pitch), a nonlinearity, and a WFS with a gain and white noise.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import ClassVar

import numpy as np

from eofnn.delay import DELAY, check_delay, split_delay
from eofnn.errors import ConfigError, require
from eofnn.lazy import lazy_module
from eofnn.sim.atmosphere.changes import DmGainDrift, build_drift
from eofnn.sim.grid import ActuatorGrid
from eofnn.validation import Constraint, Interval, OneOf, validated

torch = lazy_module("torch")

NONLINEARITIES = ("none", "tanh", "quadratic")


@dataclass(frozen=True)
@validated
class Plant:
    """Loop delay and model errors.

    Parameters
    ----------
    delay_frames : int or float
        Loop delay ``tau >= 1`` in frames (2 in the reference study). An integer ``d``: ``y(n)`` uses ``eps`` up to
        ``eps(n - d)``. A fraction ``tau = d + f`` (Keck's 1.5 ms at 1 kHz: 1.5): ``y(n)`` still uses ``eps`` up to
        ``eps(n - d)``, and the DM shape during frame ``n`` is the time average of the commands acting over it,
        ``(1 - f) DM(y(n)) + f DM(y(n - 1))`` (see :mod:`eofnn.delay`).
    dm_gain : float
        The DM applies ``dm_gain * y`` (1 is nominal).
    misregistration_x : float
        Shift along x of the applied DM shape relative to the controller's model, in actuator pitches (|x| <= 10).
    misregistration_y : float
        Shift along y of the applied DM shape relative to the controller's model, in actuator pitches (|y| <= 10).
    nonlinearity : str
        DM response: ``"none"``, ``"tanh"`` (saturates at ``nonlinearity_scale_nm``) or ``"quadratic"``
        (``y + y**2 / nonlinearity_scale_nm``).
    nonlinearity_scale_nm : float
        Scale of the nonlinearity in nm.
    wfs_noise_nm : float
        RMS of white WFS noise per actuator and frame, in nm.
    wfs_gain : float
        The WFS reports ``wfs_gain * eps`` (optical gain; 1 is nominal).
    dm_gain_drift : DmGainDrift, optional
        ``{start_s, stop_s, to}``: the DM gain moves linearly from ``dm_gain`` to ``to`` between the two times
        (:mod:`eofnn.sim.atmosphere.changes`); the stability analysis and the controllers' model keep the static ``dm_gain``.
    """

    delay_frames: int | float = 2
    dm_gain: float = 1.0
    misregistration_x: float = 0.0
    misregistration_y: float = 0.0
    nonlinearity: str = "none"
    nonlinearity_scale_nm: float = 1000.0
    wfs_noise_nm: float = 0.0
    wfs_gain: float = 1.0
    dm_gain_drift: DmGainDrift | None = None

    _constraints: ClassVar[dict[str, Constraint]] = {
        "delay_frames": DELAY,
        "dm_gain": Interval(0, 100, closed="right"),
        "misregistration_x": Interval(-10, 10, unit="actuator pitches"),
        "misregistration_y": Interval(-10, 10, unit="actuator pitches"),
        "nonlinearity": OneOf(NONLINEARITIES),
        "nonlinearity_scale_nm": Interval(0, 1e7, closed="right", unit="nm"),
        "wfs_noise_nm": Interval(0, 1e6, unit="nm"),
        "wfs_gain": Interval(0, 100, closed="right"),
    }

    def __post_init__(self) -> None:
        object.__setattr__(self, "delay_frames", check_delay(self.delay_frames))  # 2.0 -> 2: integers stay ints
        object.__setattr__(self, "dm_gain_drift", build_drift(self.dm_gain_drift))

    @property
    def whole_delay_frames(self) -> int:
        """``d = floor(delay_frames)``: the lag of the WFS reading the controller receives."""
        return split_delay(self.delay_frames)[0]

    @property
    def delay_fraction(self) -> float:
        """``f = delay_frames - d``: the fraction of a frame that still sees the previous command."""
        return split_delay(self.delay_frames)[1]

    @classmethod
    def model_error_names(cls) -> tuple[str, ...]:
        """Names a scenario variant may change (every field: the delay and the model errors)."""
        return tuple(f.name for f in fields(cls))

    def with_errors(self, **changes) -> Plant:
        """A copy with some fields changed; an unknown name is a one-line error."""
        allowed = self.model_error_names()
        for name in changes:
            if name not in allowed:
                raise ConfigError(f"unknown model error {name!r}: allowed are {', '.join(allowed)}")
        return replace(self, **changes)

    def to_dict(self) -> dict:
        return asdict(self)


class PlantModel:
    """A :class:`Plant` bound to an actuator grid, applying the DM and the WFS to torch tensors."""

    def __init__(self, plant: Plant, grid: ActuatorGrid, dtype: torch.dtype | None = None,
                 frame_rate_hz: float | None = None) -> None:
        """``dtype``: of the misregistration operator, ``torch.float64`` unless given."""
        dtype = torch.float64 if dtype is None else dtype
        self.plant = plant
        self.grid = grid
        self.frame_rate_hz = frame_rate_hz
        self._shift = None
        if plant.misregistration_x or plant.misregistration_y:
            self._shift = _shift_operator(grid, plant.misregistration_x, plant.misregistration_y, dtype)

    def to(self, device: torch.device | str) -> PlantModel:
        """This model with its misregistration operator on ``device`` (where the commands it applies live)."""
        if self._shift is not None:
            self._shift = tuple(t.to(device) for t in self._shift)
        return self

    def apply_dm(self, y: torch.Tensor, frame: int | None = None) -> torch.Tensor:
        """Correction the DM really applies (nm) for commands ``y`` (nm), ``(..., n_actuators)``, at ``frame``
        (the gain of a drifting DM at that frame; without a frame, the static ``dm_gain``)."""
        p = self.plant
        if self._shift is not None:
            index, weight = self._shift
            padded = torch.cat([y, torch.zeros_like(y[..., :1])], dim=-1)
            y = (padded[..., index] * weight).sum(-1)
        if p.nonlinearity == "tanh":
            y = p.nonlinearity_scale_nm * torch.tanh(y / p.nonlinearity_scale_nm)
        elif p.nonlinearity == "quadratic":
            y = y + y * y / p.nonlinearity_scale_nm
        gain = p.dm_gain
        if p.dm_gain_drift is not None and frame is not None:
            require(self.frame_rate_hz is not None, "plant.dm_gain_drift needs the frame rate: give PlantModel a "
                                                    "frame_rate_hz")
            gain = p.dm_gain_drift.gain(frame / self.frame_rate_hz, p.dm_gain)
        return gain * y if gain != 1.0 else y

    def measure(self, eps: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """WFS measurement of residual ``eps`` (nm): gain plus white noise drawn from ``generator``."""
        p = self.plant
        out = p.wfs_gain * eps if p.wfs_gain != 1.0 else eps
        if p.wfs_noise_nm > 0:
            out = out + p.wfs_noise_nm * torch.randn(eps.shape, generator=generator, dtype=eps.dtype)
        return out


def _shift_operator(grid: ActuatorGrid, dx: float, dy: float, dtype: torch.dtype):
    """Bilinear weights that shift an actuator map by ``(dx, dy)`` pitches; actuators off the pupil give zero."""
    n = grid.n_across
    lookup = np.full((n, n), grid.n_actuators, dtype=np.int64)
    lookup[grid.mask] = np.arange(grid.n_actuators)
    rows, cols = grid.indices.T.astype(float)
    # The applied shape at actuator k is the commanded shape at (k - shift).
    src_r, src_c = rows - dy, cols - dx
    r0, c0 = np.floor(src_r).astype(int), np.floor(src_c).astype(int)
    fr, fc = src_r - r0, src_c - c0
    index, weight = [], []
    for ddr, ddc, w in ((0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc), (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
        rr, cc = r0 + ddr, c0 + ddc
        ok = (rr >= 0) & (rr < n) & (cc >= 0) & (cc < n)
        index.append(np.where(ok, lookup[np.clip(rr, 0, n - 1), np.clip(cc, 0, n - 1)], grid.n_actuators))
        weight.append(np.where(ok, w, 0.0))
    return torch.as_tensor(np.stack(index, 1)), torch.as_tensor(np.stack(weight, 1), dtype=dtype)
