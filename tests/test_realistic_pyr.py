"""configs/realistic_pyr.yaml: the flagship's sky through eofnn's pyramid loads as such, an undersampled variant of it
is refused in one line, and a pyramid compare writes the optical gains measured on the best-gain integrator's
closed-loop residual into metrics.json."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from eofnn.sim.scenario import Scenario

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "realistic_pyr.yaml"
FLAGSHIP = ROOT / "configs" / "flagship_sh.yaml"


def test_realistic_pyr_is_the_flagships_sky_and_pitch_through_a_pyramid():
    pyr, sh = yaml.safe_load(CONFIG.read_text()), yaml.safe_load(FLAGSHIP.read_text())
    scenario = Scenario.from_dict(pyr["scenario"])
    assert scenario.sensor.is_pyramid
    sky, flagship = pyr["scenario"], sh["scenario"]
    for key in ("r0_m", "r0_wavelength_m", "outer_scale_m", "layers", "model", "remove_ptt"):
        assert sky["atmosphere"][key] == flagship["atmosphere"][key]
    assert scenario.grid.pitch_m == flagship["grid"]["diameter_m"] / flagship["grid"]["n_across"]
    assert sky["frame_rate_hz"] == flagship["frame_rate_hz"] and sky["plant"] == flagship["plant"]
    for key in ("band", "magnitude", "throughput"):
        assert sky["sensor"]["detector"][key] == flagship["sensor"]["detector"][key]
    assert {"integrator", "lqg"} <= set(pyr["predictors"])
    # Its Shack-Hartmann twin (the command in its header) sets no field a Shack-Hartmann refuses.
    assert set(sky["sensor"]) == {"kind", "detector"}


@pytest.mark.cli
def test_realistic_pyr_in_a_poorer_sky_is_refused_as_undersampled(cli_error, tmp_path):
    """r0 = 5 cm at 500 nm is 8.7 cm in the I band: under 1.5 of the pupil's 0.1 m samples."""
    cli_error(["compare", "--config", CONFIG, "--scenario.atmosphere.r0_m", "0.05", "--out", tmp_path / "o"],
              "sensor.samples_per_pixel=2 is invalid here: the pupil is sampled every 0.1 m against r0 = 0.0866 m",
              tmp_path / "o")


@pytest.mark.slow
@pytest.mark.cli
def test_a_pyramid_compare_writes_the_integrators_optical_gains(cli, tmp_path):
    """realistic_pyr at 2 m (10 x 10 actuators, its pitch and sky), one integrator, 200 frames."""
    config = yaml.safe_load(CONFIG.read_text())
    config["scenario"]["grid"] = {"diameter_m": 2.0, "n_across": 10, "obstruction": 0.0}
    config["scenario"]["atmosphere"]["screen_frames"] = 400
    config["predictors"] = {"integrator": {"controller": "integrator", "gain": 0.5}}
    config["evaluation"] = {"frames": 200, "settle_frames": 100, "seed": 1, "psd_segment_frames": 64,
                            "analytic_stability": False}
    path = tmp_path / "tiny_pyr.yaml"
    path.write_text(yaml.safe_dump(config))
    code, err = cli("compare", "--config", path, "--out", tmp_path / "o")
    assert code == 0, err
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    gains = metrics["scenarios"]["nominal"]["integrator"]["optical_gains"]
    assert gains["n_modes"] == len(gains["gains"]) == 50
    assert gains["low_orders"] == [1, 10] and gains["high_orders"] == [26, 50]
    for value in (*gains["gains"], gains["low_order_mean"], gains["high_order_mean"]):
        assert 0 < value <= 1.2
    assert gains["residuals"] > 0 and gains["residual_rms_nm"] > 0


@pytest.mark.slow
@pytest.mark.cli
def test_simulate_reports_the_integrators_optical_gains_in_a_pyramid_scenario(cli, tmp_path):
    """``eofnn simulate`` of an integrator in a pyramid scenario (tests/conf/pyr_tiny.yaml's: 2 m, 10 across) puts
    the optical gains on its residual in the summary line it prints."""
    scenario = yaml.safe_load((ROOT / "tests" / "conf" / "pyr_tiny.yaml").read_text())["scenario"]
    path = tmp_path / "pyr.yaml"
    path.write_text(yaml.safe_dump(scenario))
    code, err = cli("simulate", "--scenario", path, "--predictor.gain", "0.5", "--frames", "150",
                    "--out", tmp_path / "run.fits")
    assert code == 0, err
    summary = json.loads(err.strip().splitlines()[-1])
    gains = summary["optical_gains"]
    assert len(gains["gains"]) == 50 and all(0 < g <= 1.2 for g in gains["gains"])
    assert 0 < gains["high_order_mean"] <= 1.2
