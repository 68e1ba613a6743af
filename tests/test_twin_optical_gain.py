"""``eofnn twin --optical_gain``: the sensor's optical gain on sky, which the dither cannot tell from the DM's gain
(it identifies their product), divides the POL before the seeing; without it r0 is of the sensor's reading of the
phase (``optical_gain^(-6/5)`` high), with a one-line warning."""

from __future__ import annotations

import pytest
import torch

from eofnn.control import Dithered, Integrator
from eofnn.errors import ConfigError
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Telemetry, run_loop
from eofnn.sim.loop.plant import Plant
from eofnn.sim.scenario import Scenario
from eofnn.training.twin import identify_twin

GRID = ActuatorGrid(2.0, 8)
OPTICAL_GAIN = 0.8


@pytest.fixture(scope="module")
def records():
    """A dithered integrator's record (8 across on 2 m, one 10 m/s layer, r0 0.12 m, 10 nm of noise), as recorded
    and as a sensor of optical gain 0.8 would have read it (its wfs times 0.8: the loop's gain is then the product)."""
    atmosphere = Atmosphere(r0_m=0.12, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=(Layer(1.0, 10.0, 30.0),),
                            screen_frames=2200)
    scenario = Scenario(GRID, atmosphere, 1000.0, Plant(delay_frames=2, wfs_noise_nm=10.0))
    result = run_loop(scenario.turbulence(2, "og_test"), scenario.plant, Dithered(Integrator(0.4), 10.0, seed=3),
                      2000, noise_seed=4, progress=False)
    t = result.telemetry.realisation(0)

    def record(scale: float) -> Telemetry:
        return Telemetry(y=t.y, wfs=t.wfs * scale, delay_frames=2, frame_rate_hz=1000.0,
                         positions_m=torch.as_tensor(GRID.positions_m))
    return record(1.0), record(OPTICAL_GAIN)


@pytest.mark.slow
def test_the_optical_gain_given_recovers_the_phases_r0_and_the_dms_gain(records):
    plain, read = records
    truth = identify_twin(plain)
    given = identify_twin(read, optical_gain=OPTICAL_GAIN)
    for name in ("r0_m", "outer_scale_m", "wfs_noise_nm"):
        assert given.value(name) == pytest.approx(truth.value(name), rel=1e-6), name
    assert given.value("dm_gain") == pytest.approx(OPTICAL_GAIN * truth.value("dm_gain"), rel=1e-6)  # the product
    assert given.twin_config()["plant"]["dm_gain"] == pytest.approx(truth.twin_config()["plant"]["dm_gain"], abs=1e-4)
    assert [lay["speed_mps"] for lay in given.layers] == pytest.approx([lay["speed_mps"] for lay in truth.layers])
    # Without it, r0 is the sensor's reading: high by about optical_gain^(-6/5) (L0 chosen from a grid may move it).
    sensed = identify_twin(read)
    assert any("give optical_gain" in w for w in sensed.warnings)
    assert not any("give optical_gain" in w for w in given.warnings)
    assert sensed.value("r0_m") / truth.value("r0_m") == pytest.approx(OPTICAL_GAIN ** -1.2, rel=0.05)


def test_an_optical_gain_out_of_range_is_refused_in_one_line(records):
    for bad in (-0.5, "measured"):
        with pytest.raises(ConfigError, match=f"optical_gain={bad!r}"):
            identify_twin(records[0], optical_gain=bad)


@pytest.mark.slow
def test_identified_takes_the_whole_product_as_the_sensors(records):
    """Where the DM's gain is its interaction matrix's, the dither's product is the optical gain: the phase's r0 again,
    the twin's DM gain 1."""
    plain, read = records
    truth, found = identify_twin(plain), identify_twin(read, optical_gain="identified")
    assert found.value("optical_gain") == pytest.approx(found.value("dm_gain"))
    assert found.value("r0_m") / truth.value("r0_m") == pytest.approx(truth.value("dm_gain") ** 1.2, rel=0.03)
    assert found.twin_config()["plant"]["dm_gain"] == 1.0

