"""The Shack-Hartmann's constants and the constraints of its config's fields, declared once for the scenario's
``sensor:`` (:mod:`eofnn.sim.sensing.sensor`) and the sensor itself (:mod:`eofnn.sim.sensing.shack_hartmann`,
:mod:`eofnn.sim.sensing.least_squares`). Light: numpy, scipy and torch stay unimported until a sensor is built."""

from __future__ import annotations

from eofnn.sim.grid import MAX_N_ACROSS
from eofnn.validation import Constraint, Interval, OneOf, OrNone

#: Subaperture geometries: ``fried`` (between four actuators), ``cell`` (one subaperture per actuator cell).
GEOMETRIES = ("fried", "cell")
#: OOPAO's default mechanical coupling (``DeformableMirror(mechCoupling=0.35)``): the influence at a neighbour.
MECHANICAL_COUPLING = 0.35
#: The constraints of a Shack-Hartmann's fields (:class:`~eofnn.sim.sensing.sensor.Sensor`'s and
#: :class:`~eofnn.sim.sensing.shack_hartmann.ShackHartmann`'s).
SHACK_HARTMANN_CONSTRAINTS: dict[str, Constraint] = {
    "geometry": OneOf(GEOMETRIES),
    "samples_per_subaperture": Interval(1, 16, integer=True, unit="fine intervals per subaperture side"),
    "subapertures_across": OrNone(Interval(2, MAX_N_ACROSS, integer=True, unit="subapertures across")),
    "mechanical_coupling": Interval(0, 1, closed="neither", unit="influence at the neighbouring actuator"),
    "relative_cut": OrNone(Interval(1e-3, 1, unit="fraction of the largest singular value")),
    "pupil_diameter_m": OrNone(Interval(0, 100, closed="right", unit="m")),
    "lit_fraction": OrNone(Interval(0, 1, closed="right", unit="of a subaperture's area")),
}
