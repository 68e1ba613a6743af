"""Slopes and the reconstructor in the telemetry eofnn writes (issue 29): a Shack-Hartmann loop records the sensor's
slopes, ``R slopes + (I - P) y = wfs``, recording them changes no other number, and ``eofnn simulate`` writes them
with the matrices so that identify, fit --telemetry and replay read the file, and a copy without ``wfs`` as anyone's
slopes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from eofnn.control.baselines import Integrator, Uncorrected
from eofnn.errors import ConfigError, TelemetryError
from eofnn.sim.loop.runner import run_loop
from eofnn.sim.scenario import Scenario
from eofnn.telemetry.record import Telemetry

GRID = {"diameter_m": 4.0, "n_across": 10, "obstruction": 0.0}  # 80 actuators, 9 x 9 Fried subapertures, 122 slopes
ATMOSPHERE = {"r0_m": 0.15, "layers": [{"wind_speed_mps": 10.0}], "screen_frames": 400}
FRAMES = 300
RECORD = ("s", "y", "eps", "wfs")
TINY_SCENARIO = Path(__file__).parent / "conf" / "tiny_scenario.yaml"


def _scenario(plant: dict, **sensor) -> Scenario:
    return Scenario.from_dict({"grid": GRID, "atmosphere": ATMOSPHERE, "plant": plant,
                               "sensor": {"kind": "shack_hartmann", **sensor}})


def _sent(y: torch.Tensor, fraction: float) -> torch.Tensor:
    """The commands acting over each frame, as the DM averages them for a fractional delay."""
    if not fraction:
        return y
    previous = torch.cat([torch.zeros_like(y[..., :1, :]), y[..., :-1, :]], -2)
    return (1 - fraction) * y + fraction * previous


@pytest.mark.slow
@pytest.mark.parametrize("plant", [{"delay_frames": 2},
                                   {"delay_frames": 1.5, "wfs_gain": 0.8, "dm_gain": 1.3, "wfs_noise_nm": 3.0}],
                         ids=["nominal", "model_errors"])
def test_recorded_slopes_make_the_measurement_and_change_no_other_number(plant):
    scenario = _scenario(plant, detector={"magnitude": 10.0})  # photon noise: about 29 nm per slope
    runs = [run_loop(scenario.turbulence(2, "test"), scenario.plant, Integrator(0.4), FRAMES, noise_seed=3,
                     record=record) for record in (RECORD, (*RECORD, "slopes"))]
    plain, recorded = runs[0].telemetry, runs[1].telemetry
    # The same turbulence, noise draws and loop, bit for bit: recording slopes costs a product, never a number.
    for name in RECORD:
        assert torch.equal(getattr(plain, name), getattr(recorded, name)), name
    assert torch.equal(runs[0].pupil_residual_rms_nm, runs[1].pupil_residual_rms_nm)
    assert plain.slopes is None and plain.reconstructor is None and "sensor" not in plain.config

    ops = scenario.turbulence(2, "test").operators
    r, d = recorded.reconstructor, recorded.interaction_matrix
    assert recorded.slopes.shape == (1, FRAMES, 122) and r.shape == (80, 122) and d.shape == (122, 80)
    torch.testing.assert_close(r @ d, ops.projector, rtol=0, atol=1e-12)  # D in the loop's command units
    # The real-time computer's measurement from the slopes: R slopes, and the command it sent in the cut modes.
    sent = _sent(recorded.y, scenario.plant.delay_fraction)
    rebuilt = recorded.slopes @ r.T + sent - sent @ (r @ d).T
    assert float((rebuilt - recorded.wfs).abs().max()) < 1e-9 * float(recorded.wfs.abs().max())
    note = recorded.config["sensor"]
    assert note["kind"] == "shack_hartmann" and note["subapertures_across"] == 9 and note["kept_modes"] == 74
    assert note["slope_noise_nm"] == pytest.approx(scenario.turbulence(2, "test").slope_noise_nm(
        scenario.plant.wfs_noise_nm))


@pytest.mark.slow
def test_slopes_are_the_sensors_own_and_their_noise_is_the_detectors():
    """Against the sensor's slope operator on the fine phase (open loop), a poke through the influence functions,
    and the noise's RMS per slope: what the recorded slopes are, not only that they make wfs."""
    scenario = _scenario({"delay_frames": 2, "wfs_gain": 0.9}, detector={"magnitude": 10.0})
    gain = scenario.plant.wfs_gain
    clean_turbulence = scenario.turbulence(2, "test", isolate="noise_free")  # the previous test's chunks
    clean = run_loop(clean_turbulence, scenario.plant, Uncorrected(), FRAMES, record=("slopes",)).telemetry
    ops = clean_turbulence.operators
    for frame in (0, 150, 290):
        phase = clean_turbulence.phase_at(frame)  # (1, n_fine)
        torch.testing.assert_close(clean.slopes[:, frame], gain * ops.sensor.slopes(phase), rtol=1e-12, atol=1e-9)
    poke = torch.zeros(1, 80, dtype=torch.float64)
    poke[0, 44] = 100.0  # 100 nm of command: its slopes on a flat wavefront, through the DM's surface
    torch.testing.assert_close(poke @ clean.interaction_matrix.T, ops.sensor.slopes(ops.surface(poke)),
                               rtol=1e-12, atol=1e-9)
    noisy_turbulence = scenario.turbulence(2, "test")
    noisy = run_loop(noisy_turbulence, scenario.plant, Uncorrected(), FRAMES, noise_seed=5,
                     record=("slopes",)).telemetry
    sigma = noisy_turbulence.slope_noise_nm(0.0)
    assert 20 < sigma < 40
    assert float((noisy.slopes - clean.slopes).std()) == pytest.approx(sigma, rel=0.03)  # 36600 draws
    with pytest.raises(ConfigError, match="isolate='perfect'"):
        run_loop(scenario.turbulence(1, "test", isolate="perfect"), scenario.plant, Uncorrected(), 10,
                 record=("slopes",))


def test_the_zonal_sensor_has_no_slopes_to_record():
    zonal = Scenario.from_dict({"grid": GRID, "atmosphere": ATMOSPHERE})
    with pytest.raises(ConfigError, match="the zonal sensor .* measures no slopes") as err:
        run_loop(zonal.turbulence(1, "test"), zonal.plant, Integrator(0.5), 10, record=("y", "slopes"))
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="allowed are s, y, eps, wfs, slopes"):
        run_loop(zonal.turbulence(1, "test"), zonal.plant, Integrator(0.5), 10, record=("slope",))


@pytest.mark.parametrize("suffix", [".fits", ".npz"])
def test_telemetry_with_slopes_and_matrices_saves_loads_and_refuses_what_does_not_fit(tmp_path, suffix):
    rng = np.random.default_rng(0)
    y, wfs = rng.normal(size=(2, 50, 6)), rng.normal(size=(2, 50, 6))
    slopes, im = rng.normal(size=(2, 50, 10)), rng.normal(size=(10, 6))
    r = np.linalg.pinv(im)
    tel = Telemetry(y=y, wfs=wfs, slopes=slopes, interaction_matrix=im, reconstructor=r,
                    config={"sensor": {"kind": "shack_hartmann"}})
    path = tel.realisation(1).save(tmp_path / f"one{suffix}", dtype="float32")
    back = Telemetry.load(path, required=("y", "wfs"))
    assert back.slopes.shape == (50, 10) and back.measurement == ""  # wfs was there: used as it is
    torch.testing.assert_close(back.slopes, torch.as_tensor(slopes[1], dtype=torch.float32).double())
    assert torch.equal(back.reconstructor, torch.as_tensor(r)) and torch.equal(back.interaction_matrix,
                                                                                torch.as_tensor(im))
    assert back.config["sensor"]["kind"] == "shack_hartmann"
    for fields, message in [({"slopes": slopes[:, :40]}, "telemetry slopes have shape (2, 40, 10)"),
                            ({"slopes": slopes, "reconstructor": im}, "telemetry reconstructor has shape (10, 6)"),
                            ({"slopes": slopes, "interaction_matrix": r}, "expected (10, 6) (slopes = IM @ y")]:
        with pytest.raises(TelemetryError, match=message.replace("(", r"\(").replace(")", r"\)")) as err:
            Telemetry(y=y, wfs=wfs, **fields)
        assert "\n" not in str(err.value)


def _drop_wfs(source: Path, target: Path) -> None:
    """A copy of eofnn's file as another system would write it: y, slopes and the reconstructor, no wfs."""
    from astropy.io import fits

    with fits.open(source) as hdul:
        keep = {hdu.name.lower(): np.asarray(hdu.data) for hdu in hdul[1:]
                if hdu.name in ("Y", "POSITIONS", "SLOPES", "RECONSTRUCTOR")}
        delay = hdul[0].header["DELAY"]
    np.savez(target, y=keep["y"], slopes=keep["slopes"], reconstructor=keep["reconstructor"],
             positions_m=keep["positions"], delay_frames=delay)


@pytest.mark.slow
@pytest.mark.cli
def test_simulate_writes_slopes_that_identify_fit_and_replay_read(tmp_path, cli):
    run, copy = tmp_path / "run.fits", tmp_path / "slopes.npz"
    code, err = cli("simulate", "--scenario", TINY_SCENARIO, "--scenario.sensor.kind", "shack_hartmann",
                    "--scenario.atmosphere.screen_frames", "400", "--predictor.controller", "dithered_integrator",
                    "--predictor.gain", "0.3", "--predictor.data.dither_nm", "30", "--frames", "400", "--out", run)
    assert code == 0, err
    written = Telemetry.load(run)
    assert written.slopes.shape == (400, 122) and written.reconstructor.shape == (80, 122)
    assert written.interaction_matrix.shape == (122, 80) and written.config["sensor"]["kind"] == "shack_hartmann"
    _drop_wfs(run, copy)
    formed = Telemetry.load(copy, required=("y", "wfs"))
    assert formed.measurement.startswith("wfs = R @ slopes with the given reconstructor (80, 122) (rank 74 of 80")
    # The two conventions differ in the 6 modes R cuts: eofnn's wfs reports there the command it sent, (I - P) y,
    # while a reader of slopes reads nothing there and removes those modes from y (y <- P y). The pseudo-open-loop
    # values wfs - y are the same either way (R slopes - P y for a whole-frame delay): so is any fit made from them.
    torch.testing.assert_close(formed.wfs - formed.y, written.wfs - written.y, rtol=0, atol=1e-9)

    plants = {}
    for name, path in (("wfs", run), ("slopes", copy)):
        code, err = cli("identify", "--telemetry", path, "--out", tmp_path / f"{name}.json")
        assert code == 0, err
        plants[name] = json.loads((tmp_path / f"{name}.json").read_text())
        code, err = cli("fit", "--telemetry", path, "--plant", "nominal", "--predictor.history", "open_loop",
                        "--predictor.history_length", "3", "--predictor.data.val_frames", "80",
                        "--out", tmp_path / f"{name}.ckpt")
        assert code == 0, err
        assert ("wfs = R @ slopes" in err) == (name == "slopes")
    # A nominal plant: both find a DM gain of 1 within their standard errors.
    for plant in plants.values():
        assert plant["identified"] and abs(plant["dm_gain"] - 1.0) < 3 * plant["dm_gain_se"] < 0.3
    weights = [torch.load(tmp_path / f"{name}.ckpt", weights_only=True)["state_dict"]["network.weight"]
               for name in ("wfs", "slopes")]
    torch.testing.assert_close(weights[1], weights[0], rtol=1e-9, atol=1e-12)

    medians = []
    for name, path in (("wfs", run), ("slopes", copy)):
        code, err = cli("replay", "--checkpoint", tmp_path / "wfs.ckpt", "--telemetry", path, "--plant", "nominal",
                        "--settle_frames", "50", "--out", tmp_path / f"replay_{name}")
        assert code == 0, err
        medians.append(json.loads((tmp_path / f"replay_{name}" / "replay.json").read_text())["predictor"]["median_rms_nm"])
    assert medians[1] == pytest.approx(medians[0], rel=1e-9)
