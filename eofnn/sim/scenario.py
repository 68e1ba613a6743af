"""A scenario: telescope (actuator grid), atmosphere, frame rate and plant — everything a loop runs in."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

from eofnn.errors import ConfigError, require
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.plant import Plant
from eofnn.sim.turbulence import Atmosphere, Layer, Turbulence


@dataclass(frozen=True)
class Scenario:
    """Where a controller is evaluated or its training data recorded.

    Parameters
    ----------
    grid : ActuatorGrid
        Telescope diameter and DM actuators.
    atmosphere : Atmosphere
        Turbulence profile.
    frame_rate_hz : float
        Loop frame rate in Hz.
    delay_frames : int
        Loop delay in frames.
    model_errors : dict
        Plant model errors by name (see :meth:`Plant.model_error_names`); empty for the nominal plant.
    """

    grid: ActuatorGrid = field(default_factory=ActuatorGrid)
    atmosphere: Atmosphere = field(default_factory=Atmosphere)
    frame_rate_hz: float = 1000.0
    delay_frames: int = 2
    model_errors: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        require(self.frame_rate_hz > 0, f"frame_rate_hz={self.frame_rate_hz!r} is invalid: it must be > 0 (Hz)")
        if isinstance(self.grid, dict):
            object.__setattr__(self, "grid", _build(ActuatorGrid, self.grid, "grid"))
        if isinstance(self.atmosphere, dict):
            object.__setattr__(self, "atmosphere", _build(Atmosphere, self.atmosphere, "atmosphere"))
        object.__setattr__(self, "model_errors", dict(self.model_errors or {}))
        _ = self.plant  # validates delay and model errors now, before anything runs

    @property
    def plant(self) -> Plant:
        return Plant.from_model_errors(self.delay_frames, self.model_errors)

    def turbulence(self, seed: int, stream: str = "test", n_realisations: int = 1) -> Turbulence:
        """The turbulence stream of this scenario for ``seed`` and ``stream``."""
        return Turbulence(self.atmosphere, self.grid, self.frame_rate_hz, seed, stream, n_realisations)

    def with_model_errors(self, **model_errors: Any) -> Scenario:
        """A copy with other model errors (the same sky and telescope)."""
        return Scenario(self.grid, self.atmosphere, self.frame_rate_hz, self.delay_frames, model_errors)

    def to_dict(self) -> dict:
        out = asdict(self)
        out["atmosphere"]["layers"] = [dict(lay) for lay in out["atmosphere"]["layers"]]
        return out

    @classmethod
    def from_dict(cls, config: dict) -> Scenario:
        return _build(cls, config, "scenario")

    @classmethod
    def from_yaml(cls, path: str | Path) -> Scenario:
        path = Path(path)
        if not path.exists():
            raise ConfigError(f"scenario file {str(path)!r} does not exist")
        data = yaml.safe_load(path.read_text()) or {}
        return cls.from_dict(data.get("scenario", data))


def _build(cls, config: dict, where: str):
    """Instantiate a config dataclass, turning unknown keys into one clear line."""
    if not isinstance(config, dict):
        raise ConfigError(f"{where} must be a mapping, got {type(config).__name__}")
    allowed = set(cls.__dataclass_fields__)
    unknown = sorted(set(config) - allowed)
    if unknown:
        raise ConfigError(f"unknown key(s) {', '.join(unknown)} in {where}: allowed are {', '.join(sorted(allowed))}")
    if cls is Atmosphere and "layers" in config:
        config = dict(config, layers=tuple(_build(Layer, lay, "layer") if isinstance(lay, dict) else lay
                                           for lay in config["layers"]))
    try:
        return cls(**config)
    except TypeError as err:  # a wrong type deep inside a comparison
        raise ConfigError(f"invalid value in {where}: {err}") from None
