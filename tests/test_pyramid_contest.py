"""experiments/pyramid/contest.yaml: the contest through eofnn's pyramid (optical gains compensated) parses as such,
and at test size runs with the open-loop EOF holding the loop, the oracle labelled and eta in metrics.json; the
open-loop training data of a pyramid scenario are POL values recorded in the loop, not the pyramid's reading of
the uncorrected turbulence (whose optical gains are far lower)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from eofnn.data.config import DataConfig
from eofnn.data.history import HistorySpec
from eofnn.data.stream import SimulatedTelemetry, open_loop_recorded
from eofnn.errors import ConfigError
from eofnn.sim.scenario import Scenario
from eofnn.training.fit import recording_controller

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "experiments" / "pyramid" / "contest.yaml"


def _tiny() -> dict:
    """The contest at 2 m (10 x 10 actuators, its pitch, sky and sensor) with short streams and 2 realisations."""
    config = yaml.safe_load(CONFIG.read_text())
    config["scenario"]["grid"] = {"diameter_m": 2.0, "n_across": 10, "obstruction": 0.0}
    config["scenario"]["atmosphere"]["screen_frames"] = 1024
    predictors = config["predictors"]
    predictors["integrator"].update(gains=[0.3, 0.6], data={"frames": 200}, refine_rounds=0)
    for name in ("modal_integrator", "lqg"):
        predictors[name]["data"]["frames"] = 1024
    predictors["lqg"].update(ar_orders=[1], noise_scales=[1])
    predictors["ol_eof"]["data"] = {"frames": 400, "val_frames": 100, "sequence_frames": 500}
    predictors["oracle"]["data"] = {"frames": 800, "val_frames": 200, "sequence_frames": 500}
    config["evaluation"].update(frames=250, settle_frames=100, realisations=2, psd_segment_frames=128)
    return config


def test_the_contest_is_a_compensated_pyramid_with_an_oracle_and_a_stated_seed():
    config = yaml.safe_load(CONFIG.read_text())
    scenario = Scenario.from_dict(config["scenario"])
    assert scenario.sensor.is_pyramid and scenario.sensor.optical_gain_compensation
    assert [layer.wind_speed_mps for layer in scenario.atmosphere.layers] == [20.0]
    predictors = config["predictors"]
    assert {"integrator", "modal_integrator", "lqg", "ol_eof", "oracle"} == set(predictors)
    oracle, eof = predictors["oracle"], predictors["ol_eof"]
    assert oracle["oracle"] is True
    assert oracle["network"]["init_args"]["radius"] > eof["network"]["init_args"]["radius"]
    assert oracle["history_length"] > eof["history_length"] and oracle["data"]["frames"] > eof["data"]["frames"]
    evaluation = config["evaluation"]
    assert evaluation["realisations"] >= 3 and evaluation["seed"] == 48


def test_a_pyramids_open_loop_data_are_recorded_in_the_loop():
    """Through a pyramid the open-loop data need the recording integrator (refused in one line without it), and its
    POL values track the truth s (slope about 1): they are not the pyramid's reading of the uncorrected turbulence."""
    config = _tiny()
    scenario = Scenario.from_dict(config["scenario"])
    data = DataConfig(seed=3, sequence_frames=300)
    spec = HistorySpec.from_scenario("open_loop", 2, scenario)
    assert open_loop_recorded(scenario, data)
    with pytest.raises(ConfigError, match="needs a data_controller"):
        SimulatedTelemetry(scenario, spec, 300, data=data)
    arrays = SimulatedTelemetry(scenario, spec, 300, data=data,
                                data_controller=recording_controller(spec, data, scenario)).telemetry(0)
    s, pol = arrays["s"][:, 50:], arrays["s_hat"][:, 50:]
    slope = float((pol * s).sum() / (s * s).sum())
    assert 0.9 < slope < 1.1
    turbulence = scenario.turbulence(3, "train:0")
    s_ol, read = turbulence.open_loop(0, 300, scenario.plant, None)
    assert s_ol.equal(arrays["s"]) and not read.allclose(arrays["s_hat"], atol=1.0)


@pytest.mark.slow
@pytest.mark.cli
def test_the_tiny_contest_runs_with_the_eof_in_the_loop_the_oracle_and_eta(cli, tmp_path):
    path = tmp_path / "contest.yaml"
    path.write_text(yaml.safe_dump(_tiny()))
    code, err = cli("compare", "--config", path, "--out", tmp_path / "o")
    assert code == 0, err
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    runs = metrics["scenarios"]["nominal"]
    assert set(runs) == {"integrator", "modal_integrator", "lqg", "ol_eof", "oracle"}
    assert not any(runs[name]["diverged"] for name in runs)
    verdict = metrics["verdict"]["scenarios"]["nominal"]
    ratios = verdict["ratios"]
    assert ratios["oracle"]["name"] == "oracle" and "simulator" in ratios["oracle"]["knowledge"]
    eof = ratios["predictors"]["ol_eof"]
    assert eof["eta"] is not None and eof["variance_ratio"] > 0
    assert eof["raw_contrast"]["3"]["ratio"] > 0
