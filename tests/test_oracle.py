"""The oracle of a contest: the least-squares filter fitted on the simulator's truth with more reach than any
contender. It is a bound only if no contender beats it beyond the realisations' scatter: checked here in the tiny
zonal scenario and in a small Shack-Hartmann one."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
from eofnn.evaluation.contenders import ORACLE_EXTRA_TAPS, ORACLE_FRAMES_FACTOR, oracle_config
from eofnn.evaluation.experiment import Experiment
from eofnn.sim.scenario import Scenario

TINY = Path(__file__).parent / "conf" / "tiny_scenario.yaml"
NEIGHBOURS = {"class_path": "eofnn.models.linear.LinearFilter", "init_args": {"structure": "neighbourhood",
                                                                               "radius": 1.5}}


def tiny() -> Scenario:
    return Scenario.from_dict(yaml.safe_load(TINY.read_text()))


def shack_hartmann() -> Scenario:
    """8 subapertures across 3.2 m, an I = 8 star (photon noise), one 10 m/s layer: a real sensor in seconds."""
    return Scenario.from_dict({"grid": {"diameter_m": 3.2, "n_across": 8, "obstruction": 0.0},
                               "atmosphere": {"r0_m": 0.15, "layers": [{"wind_speed_mps": 10.0}]},
                               "plant": {"delay_frames": 2},
                               "sensor": {"kind": "shack_hartmann", "detector": {"magnitude": 8.0}}})


def test_an_oracle_must_learn_from_the_truth_and_is_refused_otherwise_in_one_line():
    for kwargs, said in (({"controller": "integrator"}, "not controller='integrator'"),
                         ({"data": {"truth": False}}, "with data.truth: false"),
                         ({"checkpoint": "x.ckpt"}, "with checkpoint='x.ckpt'")):
        with pytest.raises(ConfigError) as error:
            PredictorConfig(oracle=True, **kwargs)
        assert said in str(error.value) and "\n" not in str(error.value)
    with pytest.raises(ConfigError, match="evaluation.oracle='yes' is invalid"):
        EvaluationConfig(oracle="yes")


def test_the_oracle_reaches_further_than_every_contender():
    predictors = {"integrator": PredictorConfig(controller="integrator"),
                  "ol": PredictorConfig(history_length=5, data={"frames": 3000}),
                  "nb": PredictorConfig(history_length=3, network=NEIGHBOURS, data={"frames": 2000}),
                  "cl": PredictorConfig(history="closed_loop", history_length=6, data={"frames": 1000})}
    oracle = oracle_config(predictors, tiny())
    assert oracle.oracle and oracle.trains and oracle.data.truth and oracle.history == "open_loop"
    assert oracle.history_length == 6 + ORACLE_EXTRA_TAPS
    assert oracle.network["init_args"] == {"structure": "neighbourhood", "radius": 2.5}
    assert oracle.data.frames == max(ORACLE_FRAMES_FACTOR * 3000, 8000) and oracle.optimization.alpha == "auto"
    assert oracle.data.target == "measured" and oracle_config(predictors, shack_hartmann()).data.target == "dm_fit"
    evaluation = EvaluationConfig(frames=300, settle_frames=100, oracle=True)
    experiment = Experiment(tiny(), {"nominal": {}}, dict(predictors), evaluation, log=lambda _: None)
    assert experiment.predictors["oracle"].oracle
    with pytest.raises(ConfigError, match="already has one"):
        Experiment(tiny(), {"nominal": {}}, {"oracle": PredictorConfig()}, evaluation, log=lambda _: None)


def _contest(scenario: Scenario, predictors: dict, frames: int) -> dict:
    evaluation = EvaluationConfig(frames=frames, settle_frames=200, realisations=3, analytic_stability=False,
                                  error_budget=False, oracle=True)
    result = Experiment(scenario, {"nominal": {}}, predictors, evaluation, log=lambda _: None).run()
    return result.verdict["scenarios"]["nominal"], result.metrics["nominal"]


def _not_beaten(verdict: dict, metrics: dict) -> None:
    """No predictor's median beats the oracle's by more than the spread of its realisations' medians, and so no η
    is above 1 by more than that."""
    oracle = metrics["oracle"]
    assert verdict["ratios"]["oracle"]["name"] == "oracle"
    assert verdict["best_predictor"]["name"] != "oracle"
    for name, ratios in verdict["ratios"]["predictors"].items():
        mine = metrics[name]
        scatter = max(mine.realisation_median_rms_nm) - min(mine.realisation_median_rms_nm)
        assert oracle.median_rms_nm <= mine.median_rms_nm + scatter, name
        assert ratios["eta"] is not None and ratios["eta"] <= 1.0 + 2 * scatter / mine.median_rms_nm, name


@pytest.mark.slow
def test_no_contender_beats_the_oracle_in_the_tiny_scenario():
    predictors = {"integrator": PredictorConfig(controller="integrator", gain=0.4),
                  "ol_eof": PredictorConfig(history_length=4, optimization={"alpha": 1e-9},
                                            data={"frames": 2000, "val_frames": 400, "sequence_frames": 1000}),
                  "ol_eof_nb": PredictorConfig(history_length=4, network=NEIGHBOURS,
                                               data={"frames": 2000, "val_frames": 400, "sequence_frames": 1000}),
                  "cl_eof": PredictorConfig(history="closed_loop", history_length=5, optimization={"alpha": 1e-9},
                                            data={"frames": 2000, "val_frames": 400, "sequence_frames": 1000,
                                                  "dither_nm": 10.0, "integrator_gain": 0.25})}
    verdict, metrics = _contest(tiny(), predictors, 900)
    _not_beaten(verdict, metrics)


@pytest.mark.slow
def test_no_contender_beats_the_oracle_through_a_shack_hartmann():
    data = {"frames": 1500, "val_frames": 300, "sequence_frames": 1500}
    predictors = {"integrator": PredictorConfig(controller="integrator", gain=0.4),
                  "ol_eof": PredictorConfig(history_length=3, data=data),
                  "ol_eof_antialias": PredictorConfig(history_length=3, network=NEIGHBOURS,
                                                      data={**data, "target": "dm_fit"})}
    verdict, metrics = _contest(shack_hartmann(), predictors, 700)
    _not_beaten(verdict, metrics)
