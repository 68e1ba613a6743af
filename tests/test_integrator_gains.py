"""The best-gain integrator: compare chooses each scenario's gain on a stream of its own."""

from __future__ import annotations

import pytest

from eofnn.control.baselines import critical_gain
from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
from eofnn.evaluation.experiment import Experiment


@pytest.mark.slow
def test_the_best_gain_is_chosen_per_scenario_and_used_everywhere(small_scenario):
    gains = [0.05, 0.4, 1.5]  # 1.5 is beyond the critical gain of a two-frame delay (1): it diverges
    assert gains[-1] > critical_gain(2)
    experiment = Experiment(
        small_scenario, {"nominal": {}, "dm_gain_2": {"dm_gain": 2.0}},
        {"integrator": PredictorConfig(controller="integrator", gains=gains, data={"frames": 600, "seed": 3})},
        EvaluationConfig(frames=600, settle_frames=100, psd_segment_frames=128), log=lambda line: None)
    result = experiment.run()
    nominal, doubled = (result.integrator_gains[s]["integrator"] for s in ("nominal", "dm_gain_2"))
    assert nominal["scanned"]["1.5"] is None and doubled["scanned"]["1.5"] is None  # diverged, reported
    for scan, plant_gain in ((nominal, 1.0), (doubled, 2.0)):
        finite = {g: v for g, v in scan["scanned"].items() if v is not None}
        assert float(min(finite, key=finite.get)) == scan["gain"]
        # Refined between the grid's gains (0.05 lags the turbulence, 1.5 diverges): never an edge of the grid.
        assert len(scan["refined"]) >= 3 and not scan["at_edge"]
        assert scan["critical_gain"] == pytest.approx(critical_gain(2) / plant_gain, rel=1e-9)
        assert all(g < scan["critical_gain"] for g in scan["refined"])
    # The chosen gain is what runs: the stability analysis sees the loop gain g * 0.4 at dm_gain 2.
    assert result.stability["nominal"]["integrator"]["stable"]
    low, high = result.stability["dm_gain_2"]["integrator"]["dm_gain_interval"]
    assert high == pytest.approx(critical_gain(2) / doubled["gain"], rel=1e-6)
    assert result.to_json()["integrator_gains"]["nominal"]["integrator"]["gain"] == nominal["gain"]


@pytest.mark.slow
def test_a_grid_whose_best_is_its_top_is_extended_towards_the_critical_gain(small_scenario):
    experiment = Experiment(
        small_scenario, {"nominal": {}},
        {"integrator": PredictorConfig(controller="integrator", gains=[0.05, 0.1], data={"frames": 600, "seed": 3})},
        EvaluationConfig(frames=600, settle_frames=100, psd_segment_frames=128), log=lambda line: None)
    scan = experiment.run().integrator_gains["nominal"]["integrator"]
    assert scan["gain"] > 0.1 and scan["gain"] in scan["refined"]


@pytest.mark.parametrize("config, expected", [
    ({"controller": "predictor", "gains": [0.3]}, "gains=[0.3] is for controller: integrator"),
    ({"controller": "integrator", "gains": []}, "gains=[] is invalid"),
    ({"controller": "integrator", "gains": [0.3, 20.0]}, "integrator gain=20.0 is invalid"),
])
def test_bad_gain_lists_are_one_line_errors(config, expected):
    with pytest.raises(ConfigError, match=expected.replace("[", r"\[").replace("]", r"\]")):
        PredictorConfig(**config)
