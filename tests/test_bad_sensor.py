"""The scenario's sensor refuses what it cannot run, in one line each, as a new user meets it: a tiny YAML run with
``eofnn compare``."""

from __future__ import annotations

import pytest

from eofnn.errors import ConfigError
from eofnn.sim.grid import MAX_N_ACROSS
from eofnn.sim.scenario import Scenario
from eofnn.sim.sensing import sensor, shack_hartmann

TINY = """scenario:
  grid: {{diameter_m: 2.0, n_across: 10}}
  atmosphere: {{r0_m: 0.15, layers: [{{wind_speed_mps: 10.0}}], screen_frames: 400}}
  sensor: {sensor}
predictors:
  integrator: {{controller: integrator, gain: 0.4}}
evaluation: {{frames: 200, settle_frames: 50}}
"""


@pytest.mark.cli
@pytest.mark.parametrize(("value", "expected"), [
    ("5", "line 4: scenario.sensor=5 is invalid: it must be a mapping of Sensor fields"),
    ("[shack_hartmann]", "scenario.sensor=a list is invalid: it must be a mapping of Sensor fields"),
    ("{kind: shack_hartmann, pupil_diameter_m: 0.01}",
     "sensor.pupil_diameter_m=0.01 is invalid: a pupil narrower than one subaperture (0.2 m on this grid) lights none"),
    ("{kind: shack_hartmann, geometry: cell, subapertures_across: 4, pupil_diameter_m: 0.4}",
     "sensor.pupil_diameter_m=0.4 is invalid: a pupil narrower than one subaperture (0.5 m on this grid)"),
    ("{kind: pyramidd}", "kind='pyramidd' is invalid: it must be one of subaperture, shack_hartmann, pyramid"),
    ("{kind: pyramid, modulation_lambda_over_d: -3}",
     "modulation_lambda_over_d=-3.0 is invalid: it must be null or a finite number in [0, 255]"),
])
def test_a_sensor_that_cannot_run_is_one_line(cli_error, tmp_path, value, expected):
    config = tmp_path / "bad.yaml"
    config.write_text(TINY.format(sensor=value))
    cli_error(["compare", "--config", config, "--out", tmp_path / "o"], expected, tmp_path / "o")


def test_a_pupil_one_subaperture_across_runs():
    scenario = Scenario.from_dict({"grid": {"diameter_m": 2.0, "n_across": 10}, "atmosphere": {"screen_frames": 100},
                                   "sensor": {"kind": "shack_hartmann", "pupil_diameter_m": 0.2}})
    assert scenario.sensor.subaperture_pitch_m(scenario.grid) == pytest.approx(0.2)
    with pytest.raises(ConfigError, match="lights none of them; allowed 0.2 to 2 m"):
        Scenario.from_dict({**scenario.to_dict(), "sensor": {"kind": "shack_hartmann", "pupil_diameter_m": 0.19}})


def test_the_sensor_constants_are_declared_once():
    """The light config declares them; the sensor and its reconstructor use those very objects."""
    from eofnn.sim.sensing import least_squares

    assert shack_hartmann.GEOMETRIES is sensor.GEOMETRIES
    assert least_squares.MECHANICAL_COUPLING is sensor.MECHANICAL_COUPLING
    assert shack_hartmann.ShackHartmann._constraints is sensor.SHACK_HARTMANN_CONSTRAINTS
    own = ("kind", "reconstructor", "optical_gain_compensation", *sensor.PYRAMID_ONLY)
    assert {k: v for k, v in sensor.Sensor._constraints.items() if k not in own} == sensor.SHACK_HARTMANN_CONSTRAINTS
    # The pyramid's too: the config and the scenario's sensor share the very constraints.
    from eofnn.sim.sensing import pyramid

    assert pyramid.Pyramid._constraints is sensor.PYRAMID_CONSTRAINTS
    assert all(sensor.Sensor._constraints[name].inner is sensor.PYRAMID_CONSTRAINTS[name]
               for name in sensor.PYRAMID_ONLY)
    assert str(MAX_N_ACROSS) in sensor.SHACK_HARTMANN_CONSTRAINTS["subapertures_across"].describe()
