"""Plant identification from dithered closed-loop telemetry simulated by eofnn (the plant is unknown to it)."""

from __future__ import annotations

import warnings

import pytest
import torch

from eofnn.control import Dithered, Integrator
from eofnn.errors import OutputExistsError, TelemetryError
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Telemetry, run_loop
from eofnn.sim.loop.plant import Plant, PlantModel
from eofnn.sim.scenario import Scenario
from eofnn.training.identify import IdentifiedPlant, PlantNotIdentifiedWarning, identify_plant

PLANTS = {
    "gain": {"dm_gain": 2.0},
    "misregistration": {"misregistration_x": 0.2},
    "both_noisy": {"dm_gain": 2.0, "misregistration_x": 0.2, "misregistration_y": -0.1, "wfs_noise_nm": 5.0},
}


def scenario(**model_errors) -> Scenario:
    """12 actuators across a 2 m pupil (112 active), one 10 m/s layer, 1 kHz, two-frame delay."""
    atmosphere = Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=(Layer(1.0, 10.0, 0.0),))
    return Scenario(ActuatorGrid(2.0, 12), atmosphere, 1000.0, Plant(delay_frames=2, **model_errors))


def record(model_errors: dict, dither_nm: float = 10.0, frames: int = 3000) -> Telemetry:
    """Integrator (gain 0.3: stable for a DM gain up to 3) plus white dither, the usual data controller."""
    sc = scenario(**model_errors)
    result = run_loop(sc.turbulence(0, "identify"), sc.plant, Dithered(Integrator(0.3), dither_nm, seed=1), frames,
                      noise_seed=2)
    return result.telemetry.realisation(0)


@pytest.fixture(scope="module")
def telemetry() -> dict[str, Telemetry]:
    return {name: record(errors) for name, errors in PLANTS.items()}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(PLANTS))
def test_identifies_gain_misregistration_lag_and_noise(telemetry, name):
    truth = {"dm_gain": 1.0, "misregistration_x": 0.0, "misregistration_y": 0.0, "wfs_noise_nm": 0.0, **PLANTS[name]}
    plant = identify_plant(telemetry[name])
    assert plant.identified and plant.lag_frames == 0 and not plant.warnings
    assert abs(plant.dm_gain / truth["dm_gain"] - 1) < 0.02
    assert abs(plant.misregistration_x - truth["misregistration_x"]) < 0.02
    assert abs(plant.misregistration_y - truth["misregistration_y"]) < 0.02
    # The reported standard errors are honest: the errors are a few of them at most, and they are small.
    for key in ("dm_gain", "misregistration_x", "misregistration_y"):
        error, se = abs(getattr(plant, key) - truth[key]), getattr(plant, f"{key}_se")
        assert 0 < se < 0.01 and error < 5 * se + 1e-3, (key, error, se)
    # The dither is recovered: 10 nm RMS.
    assert plant.excitation_rms_nm == pytest.approx(10.0, rel=0.05)
    if truth["wfs_noise_nm"]:
        assert plant.wfs_noise_nm == pytest.approx(truth["wfs_noise_nm"], rel=0.2)
    else:  # the structure-function floor of noise-free frozen flow stays far below a nanometre
        assert plant.wfs_noise_nm < 1.0
    # Per-actuator gains: the interior ones scatter around the global gain; rim actuators lose off-pupil sources.
    gains = torch.tensor(plant.actuator_gains)
    interior = (torch.tensor(plant.neighbours) < len(gains)).all(1)
    assert (gains[interior] / truth["dm_gain"] - 1).abs().median() < 0.03


@pytest.mark.slow
def test_identified_response_reproduces_the_plant(telemetry):
    plant = identify_plant(telemetry["both_noisy"])
    sc = scenario(**PLANTS["both_noisy"])
    y = torch.randn(50, sc.grid.n_actuators, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    true = PlantModel(sc.plant, sc.grid).apply_dm(y)
    for kind in ("model", "sparse"):
        fitted = plant.dm_response(kind)(y)
        assert ((fitted - true).norm() / true.norm()) < (0.02 if kind == "model" else 0.1), kind
    assert set(plant.model_errors()) == {"dm_gain", "misregistration_x", "misregistration_y"}
    assert plant.plant().dm_gain == pytest.approx(plant.dm_gain)


@pytest.mark.slow
def test_json_round_trip(telemetry, tmp_path):
    plant = identify_plant(telemetry["gain"])
    path = tmp_path / "plant.json"
    plant.to_json(path)
    back = IdentifiedPlant.from_json(path)
    assert back == plant
    with pytest.raises(OutputExistsError):
        plant.to_json(path)


@pytest.mark.slow
@pytest.mark.parametrize("late", [1, 2])
def test_finds_a_late_wfs_and_realigns(telemetry, late):
    tel = telemetry["both_noisy"]
    shifted = Telemetry(y=tel.y[late:], wfs=tel.wfs[:-late], delay_frames=2, positions_m=tel.positions_m)
    plant = identify_plant(shifted)
    assert plant.lag_frames == late and "realigned" in plant.warnings[0]
    assert abs(plant.dm_gain / 2.0 - 1) < 0.02 and abs(plant.misregistration_x - 0.2) < 0.02


def test_no_dither_is_flagged():
    tel = record({"dm_gain": 2.0}, dither_nm=0.0, frames=1000)
    with pytest.warns(PlantNotIdentifiedWarning, match="cannot be identified"):
        plant = identify_plant(tel)
    assert not plant.identified and plant.dm_gain is None and "no excitation" in plant.warnings[0]
    with pytest.raises(TelemetryError, match="not identified"):
        plant.model_errors()
    assert '"identified": false' in plant.to_json()


@pytest.mark.slow
def test_bad_input(telemetry):
    tel = telemetry["gain"]
    # Without positions the gain and lag are identified (they need no geometry), the misregistration is skipped.
    bare = identify_plant(Telemetry(y=tel.y, wfs=tel.wfs, delay_frames=2))
    assert bare.identified and abs(bare.dm_gain / 2 - 1) < 0.02 and bare.lag_frames == 0 and bare.grid == {}
    assert bare.misregistration_x is None and "no actuator positions" in bare.warnings[0]
    assert bare.model_errors() == {"dm_gain": bare.dm_gain}
    with pytest.raises(TelemetryError, match="frames"):
        identify_plant(Telemetry(y=tel.y[:100], wfs=tel.wfs[:100], delay_frames=2, positions_m=tel.positions_m))
    with pytest.raises(TelemetryError, match="actuators"):
        identify_plant(tel, ActuatorGrid(2.0, 10))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a dithered recording identifies without any warning
        identify_plant(tel)


@pytest.mark.slow
def test_batches_and_several_files_pool(telemetry):
    """Realisations of a batch and separate files are independent sequences of one plant: errors shrink."""
    sc = scenario(**PLANTS["gain"])
    batch = run_loop(sc.turbulence(0, "identify-batch", 2), sc.plant, Dithered(Integrator(0.3), 10.0, seed=3), 3000,
                     noise_seed=4).telemetry
    single = identify_plant(telemetry["gain"])
    pooled = identify_plant([telemetry["gain"], batch])
    assert pooled.n_sequences == 3 and abs(pooled.dm_gain / 2.0 - 1) < 0.01
    assert pooled.dm_gain_se < 0.75 * single.dm_gain_se


@pytest.mark.parametrize(("gain", "se", "message"), [(231.4, 210.0, "unusable: DM gain 231 with a standard error"),
                                                     (-34.6, 80.0, "unusable: DM gain -34.6"),
                                                     (-1.0, 0.01, "unusable: DM gain -1: either wfs has the opposite sign")])
def test_a_plant_identified_too_poorly_to_use_is_refused_in_one_line(gain, se, message):
    plant = IdentifiedPlant(identified=True, delay_frames=2, grid={}, dm_gain=gain, dm_gain_se=se)
    with pytest.raises(TelemetryError, match=message) as err:
        plant.model_errors()
    assert "\n" not in str(err.value)
