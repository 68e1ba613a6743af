"""The whole path from a user's telemetry: ``eofnn twin`` -> ``eofnn fit --scenario DIR/twin.yaml`` (trained in the
twin) -> the guard on the user's own telemetry (``eofnn replay``) -> ``eofnn export`` of the guarded filter."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from eofnn.control import Dithered, Integrator
from eofnn.sim import run_loop
from eofnn.sim.scenario import Scenario

FRAMES = 2000
#: The user's system: a small Shack-Hartmann loop (8 actuators across 2 m, an R = 7 guide star), one 15 m/s layer.
SYSTEM = {"grid": {"diameter_m": 2.0, "n_across": 8, "obstruction": 0.0},
          "atmosphere": {"r0_m": 0.10, "r0_wavelength_m": 5e-7, "outer_scale_m": 20.0, "model": "exact",
                         "screen_frames": FRAMES + 200,
                         "layers": [{"cn2_fraction": 1.0, "wind_speed_mps": 15.0, "wind_direction_deg": 30.0}]},
          "frame_rate_hz": 1000.0, "plant": {"delay_frames": 2},
          "sensor": {"kind": "shack_hartmann", "detector": {"band": "R", "magnitude": 7.0}}}
#: The twin-trained predictor's fit: small, so that the chain stays a few seconds.
FIT = ["--predictor.data.frames", 2000, "--predictor.data.val_frames", 500, "--predictor.data.sequence_frames", 2500]


@pytest.fixture(scope="module")
def user_system(tmp_path_factory):
    """The user's record (dithered integrator, gain 0.4, 30 nm of dither) written as a real-time computer would: y,
    wfs, positions, delay and frame rate in loop.npz, the interaction matrix and reconstructor beside it; nothing of
    the simulator's settings."""
    scenario = Scenario.from_dict(SYSTEM)
    result = run_loop(scenario.turbulence(4, "user"), scenario.plant, Dithered(Integrator(0.4), 30.0, seed=5), FRAMES,
                      noise_seed=6, record=("y", "wfs", "slopes"), progress=False)
    t = result.telemetry
    folder = tmp_path_factory.mktemp("user")
    np.savez(folder / "loop.npz", y=t.y[0].numpy(), wfs=t.wfs[0].numpy(), positions_m=np.asarray(scenario.grid.positions_m),
             delay_frames=2, frame_rate_hz=1000.0)
    np.save(folder / "im.npy", t.interaction_matrix.numpy())
    np.save(folder / "r.npy", t.reconstructor.numpy())
    return folder


@pytest.fixture(scope="module")
def twin_trained(user_system, tmp_path_factory):
    """The twin of the user's record and a predictor fitted in it (the DM's fit of the true phase as target)."""
    from eofnn.cli.main import main

    folder = user_system
    assert main(["twin", "--telemetry", str(folder / "loop.npz"), "--interaction_matrix", str(folder / "im.npy"),
                 "--reconstructor", str(folder / "r.npy"), "--screen_frames", "3000", "--out",
                 str(folder / "twin")]) == 0
    assert main(["fit", "--scenario", str(folder / "twin" / "twin.yaml"), "--predictor.data.target", "dm_fit",
                 *map(str, FIT), "--out", str(folder / "twin_eof.ckpt")]) == 0
    return folder


@pytest.mark.slow
@pytest.mark.cli
def test_fit_trains_in_the_twin(twin_trained):
    """``eofnn fit --scenario DIR/twin.yaml --predictor.data.target dm_fit`` writes a checkpoint trained in the twin's
    scenario (its resolved config holds the twin's identified atmosphere, not the user's)."""
    from eofnn.training.checkpoint import load_predictor

    ckpt = twin_trained / "twin_eof.ckpt"
    predictor = load_predictor(ckpt)
    assert predictor.n_actuators == 52 and predictor.spec.delay_frames == 2
    config = yaml.safe_load((twin_trained / "twin_eof.ckpt.yaml").read_text())
    twin = yaml.safe_load((twin_trained / "twin" / "twin.yaml").read_text())
    assert config["predictor"]["data"]["target"] == "dm_fit"
    assert config["scenario"]["atmosphere"]["layers"][0]["wind_speed_mps"] == twin["atmosphere"]["layers"][0][
        "wind_speed_mps"] != 15.0
    assert config["scenario"]["sensor"]["kind"] == "shack_hartmann"


def test_guard_decides_with_the_fallbacks_statistic():
    """A predictor whose error is below the own controller's by much more than the blocks' scatter is deployed; one
    whose error is the same, or above, is not."""
    from eofnn.evaluation.fallback import decide_on_telemetry

    rng = np.random.default_rng(0)
    own = 100.0 + rng.normal(0, 5, 4000)
    assert decide_on_telemetry(own - 20.0, own)["deployed"] == "predictor"
    same = decide_on_telemetry(own + rng.normal(0, 1, 4000), own)
    assert same["deployed"] == "own_controller" and "kept" in same["why"]
    assert decide_on_telemetry(own + 20.0, own)["gain_nm2"] < 0


@pytest.mark.slow
@pytest.mark.cli
def test_guard_on_the_users_telemetry_accepts_the_twin_trained_and_refuses_a_useless_one(twin_trained, cli):
    import json

    import torch

    from eofnn.evaluation.replay import replay
    from eofnn.telemetry.record import TELEMETRY_REQUIRED, Telemetry
    from eofnn.training.checkpoint import load_predictor

    code, err = cli("replay", "--checkpoint", twin_trained / "twin_eof.ckpt", "--telemetry", twin_trained / "loop.npz",
                    "--start", 1000, "--out", twin_trained / "guard")
    assert code == 0, err
    guard = json.loads((twin_trained / "guard" / "replay.json").read_text())["guard"]
    assert guard["deployed"] == "predictor" and guard["gain_nm2"] > guard["sigmas"] * guard["scatter_nm2"], guard
    useless = load_predictor(twin_trained / "twin_eof.ckpt")
    with torch.no_grad():
        for p in useless.network.parameters():
            p.zero_()
    record = Telemetry.load(twin_trained / "loop.npz", required=TELEMETRY_REQUIRED)
    refused = replay(useless.network, useless.spec, record, start=1000).guard
    assert refused["deployed"] == "own_controller" and refused["gain_nm2"] < 0, refused


@pytest.mark.slow
@pytest.mark.cli
def test_export_of_the_guarded_filter_reproduces_the_checkpoint(twin_trained, cli, cli_error, tmp_path):
    """The exported FITS loads in eofnn.runtime and gives the
    checkpoint's commands; a guard of another checkpoint, or one that kept the own controller, is refused in one line."""
    import json

    import torch

    from eofnn.control.predictive import PredictiveController
    from eofnn.runtime import PredictiveFilter
    from eofnn.sim import LoopInput
    from eofnn.training.checkpoint import load_predictor

    ckpt, guard = twin_trained / "twin_eof.ckpt", twin_trained / "guard" / "replay.json"
    if not guard.exists():
        code, err = cli("replay", "--checkpoint", ckpt, "--telemetry", twin_trained / "loop.npz", "--start", 1000,
                        "--out", twin_trained / "guard")
        assert code == 0, err
    code, err = cli("export", "--checkpoint", ckpt, "--guard", guard, "--out", tmp_path / "filter.fits")
    assert code == 0 and '"deployed": "predictor"' in err, err
    runtime = PredictiveFilter.from_file(tmp_path / "filter.fits")
    predictor = load_predictor(ckpt)
    controller = PredictiveController(predictor.network, predictor.spec, 1.0)
    controller.reset(1, 52, 2, torch.float64)
    gen = torch.Generator().manual_seed(1)
    for n in range(30):
        wfs = 50 * torch.randn(1, 52, generator=gen, dtype=torch.float64)
        expected = controller.step(LoopInput(n, wfs, torch.zeros_like(wfs)))[0].numpy()
        assert np.abs(runtime.step(wfs[0].numpy()) - expected).max() < 1e-9
    other = tmp_path / "other.ckpt"
    other.write_bytes(ckpt.read_bytes() + b"\0")
    cli_error(["export", "--checkpoint", other, "--guard", guard, "--out", tmp_path / "f2.fits"],
              "did not replay checkpoint", tmp_path / "f2.fits")
    kept = json.loads(guard.read_text())
    kept["guard"].update(deployed="own_controller", why="refused for the test")
    (tmp_path / "kept.json").write_text(json.dumps(kept))
    cli_error(["export", "--checkpoint", ckpt, "--guard", tmp_path / "kept.json", "--out", tmp_path / "f3.fits"],
              "kept the telemetry's own controller (refused for the test): nothing exported", tmp_path / "f3.fits")


def test_a_shack_hartmann_twin_without_identified_noise_is_refused_in_one_line():
    """A bright guide star's noise estimate can be all aliasing: 0 nm identified gives one line, not a traceback."""
    from eofnn.errors import TelemetryError
    from eofnn.training.twin import Estimate, TwinIdentification

    result = TwinIdentification(sensor="shack_hartmann", estimates={"wfs_noise_nm": Estimate(0.0, None, "nm", "C_v")})
    with pytest.raises(TelemetryError, match="identified as 0 nm"):
        result.twin_config(1000)
