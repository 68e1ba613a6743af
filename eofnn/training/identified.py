"""What plant identification found (:func:`eofnn.training.identify.identify_plant`): the DM response, gain, lag and
noise with their standard errors, saved as ``plant.json`` and turned back into a DM model."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from eofnn.errors import ConfigError, TelemetryError, require
from eofnn.outputs import check_output_file, write_text_atomic
from eofnn.sim.layout import dm_model, layout_from_dict
from eofnn.sim.loop.plant import Plant

#: The largest standard error of an identified DM gain, relative to the gain, that the fits and replays use.
USABLE_GAIN_ERROR = 0.25


class PlantNotIdentifiedWarning(UserWarning):
    """The telemetry holds no excitation (dither): the plant cannot be identified from it."""


@dataclass
class IdentifiedPlant:
    """What :func:`identify_plant` found, with standard errors (``*_se``); ``None`` where nothing was identified.

    Gains are dimensionless (nm applied per nm commanded), misregistrations in actuator pitches (x = columns,
    y = rows of :class:`~eofnn.sim.grid.ActuatorGrid`, or x and y of a layout's positions), noise in nm RMS per
    actuator and frame, lags in frames. ``coupling[k][m]`` is the response of actuator ``k``'s measurement to a
    command on actuator ``neighbours[k][m]`` (``n_actuators`` marks a slot beyond the pupil edge); ``offsets[m]`` is
    that slot's (row, column) = (y, x) offset in pitches when every actuator's slot ``m`` is the same offset (a
    lattice), else empty. ``grid`` is the layout (:func:`eofnn.sim.layout.layout_from_dict`), ``{}`` without
    positions; misregistrations are None where no shift model was possible (``warnings`` says why).
    ``optical_gains`` holds the per-mode gains of a modal dither when asked for
    (:func:`eofnn.training.modal_gains.identify_modal_gains`), ``{}`` otherwise.
    """

    identified: bool
    delay_frames: int
    grid: dict
    lag_frames: int | None = None
    dm_gain: float | None = None
    dm_gain_se: float | None = None
    misregistration_x: float | None = None
    misregistration_x_se: float | None = None
    misregistration_y: float | None = None
    misregistration_y_se: float | None = None
    wfs_noise_nm: float | None = None
    wfs_noise_nm_se: float | None = None
    excitation_rms_nm: float = 0.0
    residual_rms_nm: float | None = None
    lag_response: list[float] = field(default_factory=list)
    actuator_gains: list[float] = field(default_factory=list)
    actuator_gains_se: list[float] = field(default_factory=list)
    coupling: list[list[float]] = field(default_factory=list)
    coupling_se: list[list[float]] = field(default_factory=list)
    neighbours: list[list[int]] = field(default_factory=list)
    offsets: list[list[int]] = field(default_factory=list)
    n_frames: int = 0
    n_sequences: int = 0
    settings: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    optical_gains: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    def to_json(self, path: str | Path | None = None, overwrite: bool = False) -> str:
        """The result as JSON (``plant.json``); written to ``path`` if given (an existing file only if ``overwrite``)."""
        text = json.dumps(self.to_dict(), indent=1)
        if path is not None:
            write_text_atomic(check_output_file(path, overwrite), text)
        return text

    @classmethod
    def from_json(cls, path: str | Path) -> IdentifiedPlant:
        path = Path(path)
        if not path.exists():
            raise ConfigError(f"plant file {str(path)!r} does not exist")
        try:
            return cls(**json.loads(path.read_text()))
        except (json.JSONDecodeError, TypeError) as err:
            raise ConfigError(f"plant file {str(path)!r} is not an eofnn plant.json ({type(err).__name__})") from None

    def require_identified(self) -> None:
        """One-line :class:`TelemetryError` unless the plant was identified, and well enough to use: a DM gain that is
        positive and known to :data:`USABLE_GAIN_ERROR` of itself (a dither drowned by noise, or numerical residue
        where there was none, gives a gain of any size and sign, and POL values and replays that mean nothing)."""
        if not self.identified:
            raise TelemetryError("the plant was not identified (the telemetry holds no dither): give a plant instead")
        gain, se = float(self.dm_gain), float(self.dm_gain_se or 0.0)
        if se > USABLE_GAIN_ERROR * abs(gain):
            raise TelemetryError(f"the plant identified from this telemetry is unusable: DM gain {gain:.3g} with a "
                                 f"standard error of {se:.2g} (more than {USABLE_GAIN_ERROR:.0%} of it): the dither is "
                                 "too weak for the noise and length of the recording; record longer or with a larger "
                                 "dither, or give a plant instead")
        if gain <= 0:
            raise TelemetryError(f"the plant identified from this telemetry is unusable: DM gain {gain:.3g}: either wfs "
                                 "has the opposite sign of the documented convention (eps = s + DM(y): negate the "
                                 "reconstructor, R @ IM = -I, or the wfs), or the dither "
                                 f"({self.excitation_rms_nm:.2g} nm RMS) is too weak for the WFS noise "
                                 f"({float(self.wfs_noise_nm or 0.0):.2g} nm): record with a larger dither, or give a "
                                 "plant instead")

    def model_errors(self) -> dict[str, float]:
        """``{dm_gain, misregistration_x, misregistration_y}`` for :meth:`eofnn.sim.loop.plant.Plant.with_errors`
        (without the misregistrations where none was identified)."""
        self.require_identified()
        if self.misregistration_x is None:
            return {"dm_gain": self.dm_gain}
        return {"dm_gain": self.dm_gain, "misregistration_x": self.misregistration_x,
                "misregistration_y": self.misregistration_y}

    def plant(self) -> Plant:
        """The identified plant as an eofnn :class:`~eofnn.sim.loop.plant.Plant` (linear DM, no noise)."""
        return Plant(delay_frames=self.delay_frames).with_errors(**self.model_errors())

    def dm_response(self, kind: str = "model"):
        """``y -> DM(y)`` (nm): the fitted gain + misregistration (``"model"``) or the raw coupling (``"sparse"``)."""
        self.require_identified()
        require(kind in ("model", "sparse"), f"dm_response kind={kind!r} is invalid: allowed are model, sparse")
        if kind == "model":
            errors = self.model_errors()
            return dm_model(layout_from_dict(self.grid) if self.grid else None, self.dm_gain,
                            errors.get("misregistration_x", 0.0), errors.get("misregistration_y", 0.0))
        index, weight = torch.as_tensor(self.neighbours), torch.as_tensor(self.coupling, dtype=torch.float64)

        def apply(y: torch.Tensor) -> torch.Tensor:
            padded = torch.cat([y, torch.zeros_like(y[..., :1])], dim=-1)
            return (padded[..., index] * weight).sum(-1)
        return apply
