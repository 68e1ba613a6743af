"""The Shack-Hartmann's and the pyramid's constants and the constraints of their configs' fields, declared once for the scenario's
``sensor:`` (:mod:`eofnn.sim.sensing.sensor`) and the sensor itself (:mod:`eofnn.sim.sensing.shack_hartmann`,
:mod:`eofnn.sim.sensing.least_squares`). Light: numpy, scipy and torch stay unimported until a sensor is built."""

from __future__ import annotations

from eofnn.sim.grid import MAX_N_ACROSS
from eofnn.sim.sensing.detector import PHOTOMETRY
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

#: The pyramid's signals: slopes maps or the full frame (:mod:`eofnn.sim.sensing.pyramid_optics`).
PYRAMID_SIGNALS = ("slopes_maps", "full_frame")
#: The constraints of a pyramid's fields (:class:`~eofnn.sim.sensing.pyramid.Pyramid`'s, and those
#: :class:`~eofnn.sim.sensing.sensor.Sensor` shares with it).
PYRAMID_CONSTRAINTS: dict[str, Constraint] = {
    "modulation_lambda_over_d": Interval(0, 255, unit="lambda / D"),
    "pixels_across": OrNone(Interval(2, 512, integer=True, unit="detector pixels across a pupil image")),
    "samples_per_pixel": Interval(1, 16, integer=True, unit="pupil points per detector pixel"),
    "separation_pixels": OneOf(tuple(range(0, 33, 2))),
    "modulation_points": OrNone(Interval(1, 10000, integer=True, unit="points on the modulation circle")),
    "light_ratio": Interval(0, 1, closed="left", unit="of the calibration frame's maximum"),
    "calibration_modulation_lambda_over_d": Interval(0, 1000, unit="lambda / D"),
    "signal": OneOf(PYRAMID_SIGNALS),
    "band": OneOf(tuple(PHOTOMETRY)),
    "push_pull_nm": Interval(0, 100, closed="right", unit="nm of command"),
    "mechanical_coupling": SHACK_HARTMANN_CONSTRAINTS["mechanical_coupling"],
    "relative_cut": SHACK_HARTMANN_CONSTRAINTS["relative_cut"],
    "pupil_diameter_m": SHACK_HARTMANN_CONSTRAINTS["pupil_diameter_m"],
}
#: Pupil samples a pyramid scenario's r0 (at the sensing wavelength) must span at least: the simulated focal plane,
#: ``n lambda / D`` across for ``n`` pupil points, then holds that many seeing widths ``lambda / r0``; fewer and the
#: seeing halo wraps round it (docs/findings.md: the loop does not close).
PYRAMID_MIN_R0_SAMPLES = 1.5
