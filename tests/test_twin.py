"""``eofnn twin``: a scenario identified from telemetry alone (y, wfs, positions, delay, frame rate)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from test_help_speed import imported

from eofnn.control import Dithered, Integrator
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Telemetry, run_loop
from eofnn.sim.loop.plant import Plant
from eofnn.sim.scenario import Scenario
from eofnn.training.twin import MIN_LAYER_FRAMES

GRID = ActuatorGrid(2.5, 10)


@pytest.mark.cli
@pytest.mark.parametrize("args", [["twin", "--help"], ["twin", "--telemetry", "x.npz", "--max_layers", "5", "--out", "o"]])
def test_help_and_config_errors_import_nothing_heavy(args):
    """``eofnn twin --help`` and a value out of range answer before torch & co. are imported."""
    answer = imported(args)
    assert answer["heavy"] == [] and answer["code"] == (0 if "--help" in args else 2), answer
    assert "--help" in args or "max_layers=5" in answer["stderr"]


def _random_telemetry(path, frames: int = 1200, **extra) -> None:
    rng = np.random.default_rng(0)
    k = GRID.n_actuators
    np.savez(path, y=rng.normal(size=(frames, k)), wfs=rng.normal(size=(frames, k)), positions_m=GRID.positions_m,
             delay_frames=2, frame_rate_hz=1000.0, **extra)


@pytest.mark.cli
def test_refusals_are_one_line(cli_error, tmp_path):
    """Too short a record, a mask that disagrees with the interaction matrix, a reconstructor of the wrong shape."""
    k = GRID.n_actuators
    _random_telemetry(tmp_path / "short.npz", frames=MIN_LAYER_FRAMES - 1)
    cli_error(["twin", "--telemetry", tmp_path / "short.npz", "--out", tmp_path / "a"], "too short to identify a layer",
              tmp_path / "a")
    _random_telemetry(tmp_path / "ok.npz")
    im = np.random.default_rng(1).normal(size=(2 * 81, k))
    im[:, 5] = 0.0  # actuator 5 moves no slope, yet the telemetry controls it
    np.save(tmp_path / "im.npy", im)
    cli_error(["twin", "--telemetry", tmp_path / "ok.npz", "--interaction_matrix", tmp_path / "im.npy", "--out",
               tmp_path / "b"], "actuators and its interaction matrix disagree", tmp_path / "b")
    np.save(tmp_path / "r.npy", np.ones((k + 1, 2 * 81)))
    cli_error(["twin", "--telemetry", tmp_path / "ok.npz", "--reconstructor", tmp_path / "r.npy", "--out",
               tmp_path / "c"], f"reconstructor has shape ({k + 1}, 162): expected ({k}, 2 n_sub)", tmp_path / "c")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """3000 frames of a dithered integrator on 10 actuators across 2.5 m: one 12 m/s layer at 140 degrees, r0 0.12 m
    at 500 nm, 15 nm of white WFS noise; written with y, wfs, positions, delay and frame rate only."""
    atmosphere = Atmosphere(r0_m=0.12, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=(Layer(1.0, 12.0, 140.0),),
                            screen_frames=3200)
    scenario = Scenario(GRID, atmosphere, 1000.0, Plant(delay_frames=2, wfs_noise_nm=15.0))
    result = run_loop(scenario.turbulence(4, "twin_test"), scenario.plant, Dithered(Integrator(0.4), 10.0, seed=5),
                      3000, noise_seed=6, progress=False)
    t = result.telemetry.realisation(0)
    path = tmp_path_factory.mktemp("twin") / "loop.npz"
    Telemetry(y=t.y, wfs=t.wfs, delay_frames=2, frame_rate_hz=1000.0,
              positions_m=torch.as_tensor(GRID.positions_m)).save(path)
    return path


@pytest.mark.slow
@pytest.mark.cli
def test_twin_identifies_the_system_and_its_scenario_runs(cli, cli_error, recorded, tmp_path):
    out = tmp_path / "twin"
    code, err = cli("twin", "--telemetry", recorded, "--out", out, "--screen_frames", 400)
    assert code == 0, err
    found = json.loads((out / "identified.json").read_text())
    q = found["quantities"]
    assert q["r0_m"]["value"] == pytest.approx(0.12, rel=0.15)
    assert q["wfs_noise_nm"]["value"] == pytest.approx(15.0, rel=0.2)
    assert q["dm_gain"]["value"] == pytest.approx(1.0, abs=0.05)
    assert q["layers"]["value"] == 1
    (layer,) = found["layers"]
    assert layer["speed_mps"] == pytest.approx(12.0, rel=0.1)
    assert abs((layer["direction_deg"] - 140.0 + 180) % 360 - 180) < 10
    for name in ("r0_m", "wfs_noise_nm", "dm_gain", "outer_scale_m"):
        assert q[name]["uncertainty"] is not None and math.isfinite(q[name]["uncertainty"]) and q[name]["method"]
    # The twin is a scenario eofnn runs.
    scenario = Scenario.from_yaml(out / "twin.yaml")
    assert scenario.grid == GRID and scenario.plant.delay_frames == 2
    assert scenario.atmosphere.layers[0].wind_speed_mps == pytest.approx(layer["speed_mps"], rel=1e-3)
    rms = scenario.median_residual_nm(Integrator(0.4), 200, seed=1, stream="check", settle_frames=50)
    assert rms is not None and 0 < rms < 1000
    code, err = cli("simulate", "--scenario", out / "twin.yaml", "--frames", 100, "--out", tmp_path / "run.npz")
    assert code == 0, err
    # A second run never overwrites the first without --overwrite.
    cli_error(["twin", "--telemetry", recorded, "--out", out], "not empty")


def test_noise_covariance_recovers_coloured_white_noise_under_smooth_turbulence():
    """``(4 D(1) - D(2)) / 6`` is the covariance of white noise, spatial colour included, whatever smooth signal is
    added (a random walk of drifts here stands in for slow turbulence)."""
    from eofnn.training.twin_seeing import noise_covariance

    rng = np.random.default_rng(3)
    frames, k = 20000, 6
    mixing = np.eye(k) + 0.5 * np.eye(k, k=1)  # neighbours' noise correlated
    noise = rng.normal(size=(frames, k)) @ mixing.T * 10.0
    t = np.arange(frames)[:, None] / 1000.0
    smooth = 300.0 * np.sin(2 * np.pi * (0.5 + np.arange(k)) * t)  # a few Hz: smooth over two frames
    found = noise_covariance(noise + smooth)
    truth = 100.0 * mixing @ mixing.T
    assert np.abs(found - truth).max() < 0.05 * truth.max()


def test_pupil_and_layer_bookkeeping():
    from eofnn.training.twin import pupil_from_matrices
    from eofnn.training.twin_layers import _with_errors

    k = GRID.n_actuators
    im = np.random.default_rng(2).normal(size=(20, k))
    im[[3, 17]] = 0.0  # two slopes that do not respond
    pupil = pupil_from_matrices(k, None, im, None)
    assert pupil["valid_slopes"] == 18 and pupil["dead_slopes"] == [3, 17] and pupil["valid_subapertures"] == 9

    def layer(vx, vy, weight):
        return {"vx_mps": vx, "vy_mps": vy, "speed_mps": math.hypot(vx, vy),
                "direction_deg": math.degrees(math.atan2(vy, vx)), "weight": weight}

    two = [layer(10.0, 0.0, 0.6), layer(0.0, 5.0, 0.4)]
    seen = _with_errors(two, [[layer(10.1, 0.1, 0.6), layer(0.1, 5.1, 0.4)]] * 3 + [[layer(9.9, 0.0, 0.62),
                                                                                   layer(-0.1, 4.9, 0.38)]])
    assert all(lay["found_again"] for lay in seen) and seen[0]["speed_mps_se"] < 0.1
    # A block that finds one layer only: the weaker is not found again there.
    once = _with_errors(two, [[layer(10.0, 0.0, 1.0)]] + [[layer(10.0, 0.0, 0.6), layer(0.0, 5.0, 0.4)]] * 3)
    assert once[0]["found_again"] and not once[1]["found_again"]


@pytest.mark.cli
@pytest.mark.parametrize("files, expected", [
    ({"interaction_matrix": (162, 81)}, "interaction_matrix has shape (162, 81)"),
    ({"interaction_matrix": (162, 80), "reconstructor": (80, 160)}, "reconstructor has shape (80, 160): expected "
                                                                      "(80, 2 n_sub) = (80, 162)"),
    ({"reconstructor": (80, 161)}, "reconstructor has shape (80, 161): expected (80, 2 n_sub) = (80, 161)"),
    ({"reconstructor": (80 * 162,)}, "reconstructor has dtype float64 and shape (12960,): it must be a real 2-d"),
])
def test_matrices_that_do_not_fit_the_telemetry_are_refused_in_one_line(cli_error, tmp_path, files, expected):
    """An interaction matrix for other actuators, a reconstructor for other slopes than the interaction matrix's, an
    odd number of slopes (x then y of each subaperture), a flat reconstructor: one line each, nothing written."""
    assert GRID.n_actuators == 80
    _random_telemetry(tmp_path / "ok.npz")
    args = ["twin", "--telemetry", tmp_path / "ok.npz", "--out", tmp_path / "o"]
    for name, shape in files.items():
        np.save(tmp_path / f"{name}.npy", np.random.default_rng(2).normal(size=shape))
        args[-2:-2] = [f"--{name}", tmp_path / f"{name}.npy"]
    cli_error(args, expected, tmp_path / "o")


def test_a_block_that_lands_one_component_on_noise_still_finds_the_second_layer_again(monkeypatch):
    """The count's rule on each block of the record: a block's fit has one component more than the record's, so that
    a block whose n-component fit put one component on noise (3.75 m/s where an 18 m/s layer was: seen on OOPAO's
    two-layer records) still finds the real layer among its components; a spurious third component, which moves
    from block to block, is still refused."""
    from eofnn.training import twin_layers

    def layer(speed, direction, weight):
        a = math.radians(direction)
        return {"vx_mps": speed * math.cos(a), "vy_mps": speed * math.sin(a), "speed_mps": speed,
                "direction_deg": direction, "weight": weight}

    slow, fast, ghost = layer(8.0, -10.0, 0.6), layer(18.0, -130.0, 0.4), layer(13.9, 0.0, 0.2)
    extra = [[layer(3.75, -137.0, 0.2), layer(5.0, 90.0, 0.1)], [layer(2.0, 20.0, 0.2), layer(30.0, 45.0, 0.1)],
             [layer(4.0, 170.0, 0.2), layer(25.0, -60.0, 0.1)], [layer(2.0, -100.0, 0.2), layer(28.0, 120.0, 0.1)]]
    calls = []

    def fit(x, lattice, period, n, bound, shift=None):
        if len(x) == 4000:  # the whole record: its n strongest components
            return [slow, fast, ghost][:n], 1.0, 1
        block = len(calls) % 4
        calls.append(n)
        if block == 0:  # its two-component fit misses the fast layer, a third finds it
            return [slow, extra[0][0], fast, extra[0][1]][:n], 1.0, 1
        return [slow, fast, *extra[block]][:n], 1.0, 1

    monkeypatch.setattr(twin_layers, "_layer_fit", fit)
    lattice = type("L", (), {"order": np.arange(4), "n_across": 21})()
    layers, info = twin_layers.identify_layers(np.zeros((4000, 4)), lattice, 1e-3, max_layers=3)
    assert info["chosen"] == 2 and "3 layers rejected" in info["stopped"], info
    assert [round(lay["speed_mps"]) for lay in layers] == [8, 18]


@pytest.mark.cli
def test_a_shack_hartmann_record_gives_r0_with_its_matrices_and_warns_without(cli, tmp_path):
    """eofnn's own Shack-Hartmann record (y and wfs reconstructed in command units): with its interaction matrix the
    twin's reference is the same sensor and r0 comes out right; y and wfs alone cannot tell the sensor, so the twin
    says in one line that it assumes the subaperture average (whose view of the turbulence is several times smaller
    in variance: r0 would come out less than half the truth, docs/twin.md)."""
    import yaml

    scenario = {"grid": {"diameter_m": 2.5, "n_across": 10, "obstruction": 0.0},
                "atmosphere": {"r0_m": 0.12, "r0_wavelength_m": 5e-7, "outer_scale_m": 20.0, "model": "exact",
                               "screen_frames": 1700, "remove_ptt": True,
                               "layers": [{"cn2_fraction": 1.0, "wind_speed_mps": 12.0, "wind_direction_deg": 40.0}]},
                "frame_rate_hz": 1000.0, "plant": {"delay_frames": 2},
                "sensor": {"kind": "shack_hartmann", "detector": {"band": "R", "magnitude": 9.0}}}
    (tmp_path / "sh.yaml").write_text(yaml.safe_dump(scenario))
    code, err = cli("simulate", "--scenario", tmp_path / "sh.yaml", "--predictor.controller", "dithered_integrator",
                    "--predictor.data.dither_nm", 10, "--frames", 1500, "--seed", 3, "--out", tmp_path / "full.fits")
    assert code == 0, err
    from eofnn.telemetry.record import TELEMETRY_REQUIRED
    from eofnn.training.twin import identify_twin

    full = Telemetry.load(tmp_path / "full.fits", required=TELEMETRY_REQUIRED)
    record = Telemetry(y=full.y.reshape(-1, full.y.shape[-1]), wfs=full.wfs.reshape(-1, full.wfs.shape[-1]),
                       delay_frames=2, frame_rate_hz=1000.0, positions_m=full.positions_m)
    known = identify_twin(record, interaction_matrix=full.interaction_matrix.numpy(), max_layers=1)
    assert known.sensor == "shack_hartmann"
    assert known.value("r0_m") == pytest.approx(0.12, rel=0.15)
    assert not any("subaperture average is assumed" in w for w in known.warnings)
    alone = identify_twin(record, max_layers=1)
    assert alone.sensor == "subaperture"
    assert alone.value("r0_m") < 0.5 * 0.12  # the wrong sensor's reference: why the matrices are needed
    assert any("subaperture average is assumed" in w and "interaction_matrix" in w for w in alone.warnings)
