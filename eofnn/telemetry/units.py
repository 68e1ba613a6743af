"""Units of a record's commands ``y`` and measurements ``wfs``: eofnn works in nm of smooth DM surface; a record in
another unit is converted on reading, by the factor its unit names (``--command_unit``, ``--measurement_unit`` of
``eofnn twin``, ``identify``, ``replay`` and ``fit``). Light: no numpy, so that the command line checks a unit before
anything heavy is imported."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from eofnn.validation import Constraint, Either, Interval, OneOf, OrNone, check_value

#: nm of eofnn's commands per unit: ``surface`` (eofnn's own, nm of smooth DM surface) and ``nm`` are the same.
NM_PER_UNIT = {"surface": 1.0, "nm": 1.0, "um": 1e3, "m": 1e9}
#: nm at the peak of one actuator's influence function (OOPAO's and many RTCs' commands): converted by the lattice
#: sum of the influence functions (:func:`eofnn.sim.sensing.least_squares.surface_per_command`).
PEAK = "peak"
UNITS = ("surface", "nm", PEAK, "um", "m")
#: A record's sensor's optical gain on sky as ``eofnn twin`` takes it: a number, or ``"identified"`` (all of the
#: dither's DM gain x optical gain is the sensor's: the DM's gain is its interaction matrix's).
OPTICAL_GAIN = OrNone(Either(Interval(0, 10, closed="right"), OneOf(("identified",))))


def _number(value: Any) -> float | None:
    """``value`` as a positive finite number of nm per unit, or None."""
    if isinstance(value, bool):
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) and number > 0 else None


@dataclass(frozen=True)
class Unit(Constraint):
    """A unit of commands or measurements: one of :data:`UNITS`, or a positive number of nm per unit (a record in
    volts: the DM's nm per volt)."""

    def accepts(self, value: Any) -> bool:
        return (isinstance(value, str) and value in UNITS) or _number(value) is not None

    def describe(self) -> str:
        return ("one of surface (nm of smooth DM surface, eofnn's), nm (the same), peak (nm at the peak of one "
                "actuator's influence function, OOPAO's), um, m, or a positive number of nm per unit (e.g. nm per "
                "volt)")


def check_units(command_unit: Any, measurement_unit: Any = None) -> None:
    """One :class:`~eofnn.errors.ConfigError` line for a unit that is not one."""
    check_value("command_unit", command_unit, Unit())
    if measurement_unit is not None:
        check_value("measurement_unit", measurement_unit, Unit())


def nm_per_unit(unit: Any, surface_per_peak: float) -> float:
    """eofnn's nm per one of ``unit`` (checked); ``surface_per_peak``: nm of smooth surface per nm of peak (the lattice
    sum of the DM's influence functions), used for :data:`PEAK`."""
    check_value("unit", unit, Unit())
    if isinstance(unit, str) and unit in UNITS:
        return float(surface_per_peak) if unit == PEAK else NM_PER_UNIT[unit]
    return float(_number(unit))


def conversion(command_unit: Any, measurement_unit: Any, surface_per_peak: float) -> tuple[float, float, str]:
    """``(nm per unit of y, nm per unit of wfs, one line saying so)`` (checked; ``measurement_unit`` None: the
    commands' unit; the line is "" when both are nm already)."""
    measurement_unit = command_unit if measurement_unit is None else measurement_unit
    check_units(command_unit, measurement_unit)
    command, measurement = nm_per_unit(command_unit, surface_per_peak), nm_per_unit(measurement_unit, surface_per_peak)
    if command == 1.0 and measurement == 1.0:
        return command, measurement, ""
    return command, measurement, (f"y multiplied by {command:.6g} (command_unit {command_unit}) and wfs by "
                                  f"{measurement:.6g} (measurement_unit {measurement_unit}): nm")
