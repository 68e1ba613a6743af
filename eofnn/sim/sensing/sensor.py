"""The scenario's wavefront sensor (``scenario.sensor``): today's zonal subaperture average, or a Shack-Hartmann.

- ``kind: subaperture`` (the default; nothing else to set): the loop senses the turbulence at each actuator through
  the atmosphere's sensing kernel (:mod:`eofnn.sim.sensing.kernels`) plus the plant's white ``wfs_noise_nm``. No
  slopes, no aliasing into a reconstruction, no photon statistics; the residual is scored at the actuators.
- ``kind: shack_hartmann``: the geometric Shack-Hartmann of :mod:`eofnn.sim.sensing.shack_hartmann` (Fried geometry
  by default, slopes by Gauss's theorem on a fine grid of exact frozen-flow phase, a truncated least-squares
  reconstructor) with photon and read noise from :class:`~eofnn.sim.sensing.detector.Detector` (``detector:``; none:
  noise-free) plus the plant's ``wfs_noise_nm`` as white noise per slope (nm of OPD difference across the
  subaperture). The loop then runs as :mod:`eofnn.sim.loop.sensing` describes, with the residual also scored over the
  pupil on the fine grid (fitting error included).
- ``kind: pyramid``: the diffractive modulated pyramid of :mod:`eofnn.sim.sensing.pyramid`
  (``modulation_lambda_over_d``, ``pixels_across``: one pixel per actuator pitch across the pupil by default,
  ``samples_per_pixel``), calibrated by push-pull on the DM's actuators and read through its least-squares
  reconstructor. It is not linear in the phase: the loop propagates the residual phase over the pupil each frame
  (:mod:`eofnn.sim.loop.pyramid`). The sensing band and the photon and read noise come from ``detector:`` (its band,
  magnitude, throughput and ``read_noise_e``; the I band and no noise without one).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from typing import Any, ClassVar

from eofnn.errors import ConfigError, require
from eofnn.sim.grid import ActuatorGrid

# The Shack-Hartmann's constants and field constraints are declared once, in a light module of their own.
from eofnn.sim.sensing.constants import (
    GEOMETRIES,
    MECHANICAL_COUPLING,
    PYRAMID_CONSTRAINTS,
    SHACK_HARTMANN_CONSTRAINTS,
)
from eofnn.sim.sensing.detector import Detector
from eofnn.validation import Constraint, IsBool, OneOf, OrNone, from_mapping, validated

__all__ = ["GEOMETRIES", "LOOP_SENSORS", "MECHANICAL_COUPLING", "PYRAMID_CONSTRAINTS", "SENSOR_KINDS", "Sensor",
           "build_sensor", "sensor_kinds"]

#: eofnn's own sensor kinds.
SENSOR_KINDS = ("subaperture", "shack_hartmann", "pyramid")
#: Sensors that read the turbulence on the actuator grid, by name: ``name -> factory(grid) -> LoopSensor``, filled by
#: :func:`eofnn.sim.loop.kernel.register_sensor`. A scenario's ``sensor.kind`` may name any of them.
LOOP_SENSORS: dict[str, Callable] = {}


def sensor_kinds() -> tuple[str, ...]:
    """The kinds a scenario's ``sensor.kind`` may be: eofnn's own, then the registered sensors' names."""
    return SENSOR_KINDS + tuple(sorted(set(LOOP_SENSORS) - set(SENSOR_KINDS)))


@dataclass(frozen=True)
class SensorKind(Constraint):
    """One of :func:`sensor_kinds`, as they stand when a sensor is configured (registered sensors included)."""

    def accepts(self, value: Any) -> bool:
        return isinstance(value, str) and value in sensor_kinds()

    def describe(self) -> str:
        return "one of " + ", ".join(sensor_kinds())
#: A Shack-Hartmann's reconstructors: truncated least squares, or noise-aware MMSE (:mod:`eofnn.sim.sensing.mmse`).
RECONSTRUCTORS = ("least_squares", "mmse")
#: The fields only a Shack-Hartmann has, and those only a pyramid has (the others they share).
SHACK_HARTMANN_ONLY = ("geometry", "samples_per_subaperture", "subapertures_across", "lit_fraction", "reconstructor")
PYRAMID_ONLY = ("modulation_lambda_over_d", "pixels_across", "samples_per_pixel")
#: A pyramid's modulation and samples per pixel when the scenario leaves them unset.
PYRAMID_DEFAULTS = {"modulation_lambda_over_d": 3.0, "samples_per_pixel": 2}


@dataclass(frozen=True)
@validated
class Sensor:
    """The wavefront sensor a scenario's loop runs with.

    Parameters
    ----------
    kind : {"subaperture", "shack_hartmann", "pyramid"} or a registered sensor's name
        ``subaperture`` (default): the zonal average at each actuator (the atmosphere's ``kernel``), plus the
        plant's ``wfs_noise_nm``. ``shack_hartmann``: slopes, reconstructor, photon noise (the fields below).
        ``pyramid``: a diffractive modulated pyramid (the last fields; ``mechanical_coupling``, ``relative_cut``,
        ``pupil_diameter_m`` and ``detector`` as for the Shack-Hartmann). The name of a sensor registered with
        :func:`~eofnn.sim.loop.kernel.register_sensor`: that sensor, on the actuator grid (it takes none of the fields
        below).
    geometry, samples_per_subaperture, subapertures_across, mechanical_coupling, relative_cut
        The Shack-Hartmann and its reconstructor (:class:`~eofnn.sim.sensing.shack_hartmann.ShackHartmann`):
        ``fried`` (default) or ``cell`` subapertures; fine-grid intervals per subaperture side (4); subapertures across
        (``cell`` only); the DM's mechanical coupling (0.35); the reconstructor's relative singular-value cut (``None``:
        ``min(0.1, 3 / subapertures across)``).
    pupil_diameter_m, lit_fraction
        The lit pupil (``None``: the grid's) and which subapertures are valid: ``None``, those whose centre it holds,
        taken as fully lit; a fraction, those at least that much lit, a partly lit one measuring its lit area's mean
        gradient with ``1 / lit`` times the photon noise variance (OOPAO's ``lightRatio``).
    detector : Detector or None
        Guide star and detector (band, magnitude, throughput, pixels, read noise): photon and read noise on every
        slope by Rousset's formulas (:class:`~eofnn.sim.sensing.detector.Detector`). ``None``: no photon noise.
    reconstructor : {"least_squares", "mmse"}
        ``least_squares`` (default): the truncated least-squares ``R`` (``relative_cut``). ``mmse``: the noise-aware
        ``C D^T (D C D^T + C_n)^-1`` (:mod:`eofnn.sim.sensing.mmse`) with the prior's r0 and L0 taken from the
        scenario's atmosphere (a simulation's knowledge) and the noise from this sensor's slope noise; every
        controller then measures through it (:mod:`eofnn.sim.loop.sensing`).
    modulation_lambda_over_d, pixels_across, samples_per_pixel
        The pyramid's (:class:`~eofnn.sim.sensing.pyramid.Pyramid`): modulation radius (``lambda / D``; 3 if unset),
        detector pixels across a pupil image (``None``: one per actuator pitch across the pupil, the subapertures a
        Fried Shack-Hartmann has there), pupil points per pixel (2 if unset).
    optical_gain_compensation : bool
        A pyramid's only: measure its optical gains per Karhunen-Loeve mode on the residual of a short closed loop
        of its own and divide every reconstruction by them, for every controller
        (:mod:`eofnn.sim.loop.optical_gain_compensation`). ``False`` (the default): uncompensated.
    """

    kind: str = "subaperture"
    geometry: str = "fried"
    samples_per_subaperture: int = 4
    subapertures_across: int | None = None
    mechanical_coupling: float = MECHANICAL_COUPLING
    relative_cut: float | None = None
    pupil_diameter_m: float | None = None
    lit_fraction: float | None = None
    detector: Detector | None = None
    reconstructor: str = "least_squares"
    modulation_lambda_over_d: float | None = None
    pixels_across: int | None = None
    samples_per_pixel: int | None = None
    optical_gain_compensation: bool = False

    _where: ClassVar[str] = "sensor."
    _constraints: ClassVar[dict[str, Constraint]] = {
        "kind": SensorKind(), **SHACK_HARTMANN_CONSTRAINTS, "reconstructor": OneOf(RECONSTRUCTORS),
        **{name: OrNone(PYRAMID_CONSTRAINTS[name]) for name in PYRAMID_ONLY},
        "optical_gain_compensation": IsBool()}

    def __post_init__(self) -> None:
        if self.detector is not None:
            object.__setattr__(self, "detector", from_mapping(Detector, self.detector, "sensor.detector"))
        if self.optical_gain_compensation and self.kind != "pyramid":
            raise ConfigError(f"sensor.optical_gain_compensation=True is invalid for sensor kind {self.kind!r}: only a "
                              "pyramid has optical gains to compensate; set sensor.kind: pyramid, or remove it")
        if self.kind not in ("shack_hartmann", "pyramid"):
            changed = [f.name for f in fields(self) if f.name != "kind" and getattr(self, f.name) != f.default]
            if changed:
                what = ("the zonal average has no slopes, reconstructor or detector" if self.kind == "subaperture"
                        else "a registered sensor takes none of the Shack-Hartmann's fields")
                raise ConfigError(f"sensor.{changed[0]}={getattr(self, changed[0])!r} is invalid for sensor kind "
                                  f"{self.kind!r} ({what}): set sensor.kind: shack_hartmann, or remove it")
        foreign = {"shack_hartmann": PYRAMID_ONLY, "pyramid": SHACK_HARTMANN_ONLY}.get(self.kind, ())
        defaults = {f.name: f.default for f in fields(self)}
        for name in foreign:
            if getattr(self, name) != defaults[name]:
                other = "pyramid" if self.kind == "shack_hartmann" else "shack_hartmann"
                raise ConfigError(f"sensor.{name}={getattr(self, name)!r} is invalid for sensor kind {self.kind!r}: "
                                  f"it is a field of sensor.kind: {other}; remove it")
        if self.detector is not None:
            require(math.isfinite(self.detector.magnitude), f"sensor.detector.magnitude={self.detector.magnitude!r} "
                                                            "is invalid: it must be a finite number")

    @property
    def is_shack_hartmann(self) -> bool:
        return self.kind == "shack_hartmann"

    @property
    def is_pyramid(self) -> bool:
        return self.kind == "pyramid"

    def pyramid(self):  # -> Pyramid (not imported here: jsonargparse reads this module's types)
        """The pyramid config of these fields (its band the detector's, the I band without one)."""
        from eofnn.sim.sensing.pyramid import Pyramid

        given = {name: getattr(self, name) for name in PYRAMID_ONLY if getattr(self, name) is not None}
        band = "I" if self.detector is None else self.detector.band
        return Pyramid(**{**PYRAMID_DEFAULTS, **given}, band=band, mechanical_coupling=self.mechanical_coupling,
                       relative_cut=self.relative_cut, pupil_diameter_m=self.pupil_diameter_m)

    @property
    def registered(self) -> str | None:
        """The registered sensor's name this kind names (it measures on the actuator grid), ``None`` for eofnn's own
        kinds."""
        return None if self.kind in SENSOR_KINDS else self.kind

    def shack_hartmann(self):  # -> ShackHartmann (not imported here: jsonargparse reads this module's types)
        """The Shack-Hartmann config of these fields."""
        from eofnn.sim.sensing.shack_hartmann import ShackHartmann

        return ShackHartmann(self.geometry, self.samples_per_subaperture, self.subapertures_across,
                             self.mechanical_coupling, self.relative_cut, self.pupil_diameter_m, self.lit_fraction)

    def slope_noise_nm(self, subaperture_m: float, frame_period_s: float, extra_nm: float = 0.0) -> float:
        """RMS white noise per slope (nm): the detector's photon and read noise and ``extra_nm`` in quadrature."""
        detector = 0.0 if self.detector is None else self.detector.slope_noise_variance_nm2(subaperture_m,
                                                                                             frame_period_s)
        return math.sqrt(detector + extra_nm ** 2)

    def check_fits(self, grid: ActuatorGrid) -> None:
        """Refuse up front, in one line, a Shack-Hartmann that cannot be built on ``grid``."""
        if not self.is_shack_hartmann:
            return
        if self.subapertures_across is not None and self.subapertures_across > grid.n_across:
            raise ConfigError(f"sensor.subapertures_across={self.subapertures_across!r} is invalid: the grid has "
                              f"{grid.n_across} actuators across; allowed 2 to {grid.n_across}")
        if self.pupil_diameter_m is not None and self.pupil_diameter_m > grid.diameter_m:
            raise ConfigError(f"sensor.pupil_diameter_m={self.pupil_diameter_m!r} is invalid: the actuator grid is "
                              f"{grid.diameter_m:g} m across; allowed up to that")
        pitch = self.subaperture_pitch_m(grid)
        if self.pupil_diameter_m is not None and self.pupil_diameter_m < pitch * (1 - 1e-9):
            raise ConfigError(f"sensor.pupil_diameter_m={self.pupil_diameter_m!r} is invalid: a pupil narrower than "
                              f"one subaperture ({pitch:g} m on this grid) lights none of them; allowed {pitch:g} to "
                              f"{grid.diameter_m:g} m")

    def subaperture_pitch_m(self, grid: ActuatorGrid) -> float:
        """A subaperture's side on ``grid`` (m): the actuator pitch (``fried``), or the grid's diameter over the
        subapertures across (``cell``)."""
        if self.geometry == "fried":
            return grid.pitch_m
        return grid.diameter_m / (self.subapertures_across or grid.n_across)

    def to_dict(self) -> dict:
        out = asdict(self)
        if out["reconstructor"] == "least_squares":  # configs written before the choice existed still match
            del out["reconstructor"]
        for name in PYRAMID_ONLY:  # likewise before the pyramid existed
            if out[name] is None:
                del out[name]
        if not out["optical_gain_compensation"]:  # and before its compensation
            del out["optical_gain_compensation"]
        return out


def build_sensor(value) -> Sensor:
    """A :class:`Sensor` from a scenario's ``sensor:`` value (a mapping, a Sensor or ``None``)."""
    if value is None:
        return Sensor()
    if isinstance(value, Sensor):
        return value
    if not isinstance(value, dict):
        raise ConfigError(f"sensor={value!r} is invalid: it must be a mapping such as {{kind: shack_hartmann}}")
    return from_mapping(Sensor, value, "sensor")
