"""Predictive Fourier control's memory alpha chosen per scenario on a stream of its own (``pfc_alphas``), like the
LQG's AR order and the integrator's gain; dotted settings (``pfc.alpha``) replace a section's field; bad values in
one line."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from eofnn.control.config import MAX_EXTRA_ALPHAS, alpha_past_edge
from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig, with_setting
from eofnn.evaluation.contenders import SCAN_STREAM
from eofnn.evaluation.experiment import Experiment
from eofnn.evaluation.results import describe_setting_scan
from eofnn.sim.scenario import Scenario


def test_the_setting_grid_and_a_dotted_setting_replace_the_pfcs_alpha():
    cfg = PredictorConfig(controller="pfc", pfc={"aliases": 0}, pfc_alphas=[0.99, 0.995, 0.99])
    assert cfg.setting_grid == [{"pfc.alpha": 0.99}, {"pfc.alpha": 0.995}]
    chosen = with_setting(cfg, {"pfc.alpha": 0.995})
    assert chosen.pfc.alpha == 0.995 and chosen.pfc.aliases == 0 and cfg.pfc.alpha == 0.9999
    assert with_setting(cfg, {"ar_order": 1}).ar_order == 1  # a plain field as before


@pytest.mark.parametrize("config, expected", [
    ({"controller": "pfc", "pfc_alphas": [1.0]}, "pfc_alphas=[1.0] is invalid: 1.0 is not a number from 0.5 to below 1"),
    ({"controller": "pfc", "pfc_alphas": []}, "pfc_alphas=[] is invalid: give a non-empty list"),
    ({"controller": "lqg", "pfc_alphas": [0.99]}, "pfc_alphas=[0.99] is for controller: pfc, not 'lqg'"),
])
def test_bad_pfc_alphas_are_one_line_errors(config, expected):
    with pytest.raises(ConfigError) as err:
        PredictorConfig(**config)
    assert expected in str(err.value) and "\n" not in str(err.value)


@dataclass
class _FakePfc:
    alpha: float


def test_the_alpha_scan_keeps_the_lowest_residual_on_its_own_stream(small_scenario, monkeypatch):
    """Every alpha is built (from telemetry) and closes the loop on the scan stream; the faked residuals make 0.99
    win, and the model that runs, and the config the experiment reports, are 0.99's."""
    built: list[float] = []
    calls: list[tuple] = []

    def fake_build(config, scenario):
        built.append(config.pfc.alpha)
        return _FakePfc(config.pfc.alpha)

    def fake_residual(self, controller, n_frames, seed, stream, settle_frames, **kwargs):
        calls.append((seed, stream))
        return {0.98: 5.0, 0.99: 3.0, 0.9999: 4.0}[controller.alpha]

    registry = __import__("eofnn.control.registry", fromlist=["FROM_TELEMETRY"])
    monkeypatch.setitem(registry.FROM_TELEMETRY, "pfc", fake_build)
    monkeypatch.setattr(Scenario, "median_residual_nm", fake_residual)
    experiment = Experiment(small_scenario, {"nominal": {}},
                            {"pfc": PredictorConfig(controller="pfc", pfc_alphas=[0.98, 0.99, 0.9999],
                                                    data={"frames": 1024, "seed": 5, "dither_nm": 5.0})},
                            EvaluationConfig(frames=600, settle_frames=100, seed=1), log=lambda line: None)
    config = experiment.config("pfc", "nominal")
    assert config.pfc.alpha == 0.99 and config.pfc_alphas is None
    assert built == [0.98, 0.99, 0.9999] and calls == [(5, SCAN_STREAM)] * 3
    assert experiment.predictor_if_any("pfc", "nominal") == _FakePfc(0.99)  # the chosen model, not rebuilt
    assert built == [0.98, 0.99, 0.9999]
    scan = experiment.setting_scans[("pfc", "nominal")]
    assert describe_setting_scan(scan) == "alpha 0.99 chosen (3 nm) over alpha 0.9999 (4), alpha 0.98 (5)"


def test_the_memory_goes_past_the_grids_edge_only_while_the_best_is_there():
    assert alpha_past_edge({0.98: 5.0, 0.99: 3.0}) == 0.995  # still falling at the top: twice the memory
    assert alpha_past_edge({0.98: 3.0, 0.99: 5.0}) == 0.96  # rising from the bottom: half of it
    assert alpha_past_edge({0.51: 3.0, 0.9: 5.0}) == 0.5 and alpha_past_edge({0.5: 3.0, 0.9: 5.0}) is None
    assert alpha_past_edge({0.98: 5.0, 0.99: 3.0, 0.995: 4.0}) is None  # inside the grid: done
    assert alpha_past_edge({0.98: 5.0, 0.99: 3.0, 0.995: None}) is None  # the next one up diverged
    assert alpha_past_edge({0.99: 3.0}) is None  # a single setting is no scan
    assert alpha_past_edge({0.98: 5.0, 0.99: 3.0}, extra_so_far=MAX_EXTRA_ALPHAS) is None


def test_the_alpha_scan_goes_on_past_the_grids_edge_while_the_residual_falls(small_scenario, monkeypatch):
    """Residuals lowest at 0.9975: the grid [0.98, 0.99] ends with its best at its edge, so the scan doubles the
    memory until the residual rises (0.995, 0.9975, then 0.99875) and keeps 0.9975 and its model."""
    built: list[float] = []

    def fake_build(config, scenario):
        built.append(config.pfc.alpha)
        return _FakePfc(config.pfc.alpha)

    def fake_residual(self, controller, n_frames, seed, stream, settle_frames, **kwargs):
        return 1.0 + 1e3 * abs(controller.alpha - 0.9975)

    registry = __import__("eofnn.control.registry", fromlist=["FROM_TELEMETRY"])
    monkeypatch.setitem(registry.FROM_TELEMETRY, "pfc", fake_build)
    monkeypatch.setattr(Scenario, "median_residual_nm", fake_residual)
    experiment = Experiment(small_scenario, {"nominal": {}},
                            {"pfc": PredictorConfig(controller="pfc", pfc_alphas=[0.98, 0.99],
                                                    data={"frames": 1024, "seed": 5, "dither_nm": 5.0})},
                            EvaluationConfig(frames=600, settle_frames=100, seed=1), log=lambda line: None)
    assert experiment.config("pfc", "nominal").pfc.alpha == 0.9975
    assert built == [0.98, 0.99, 0.995, 0.9975, 0.99875]
    assert experiment.predictor_if_any("pfc", "nominal") == _FakePfc(0.9975)
    scan = experiment.setting_scans[("pfc", "nominal")]
    assert [e["pfc.alpha"] for e in scan["scanned"]] == built


@pytest.mark.slow
def test_compare_builds_and_runs_the_pfc_of_the_chosen_alpha(small_scenario):
    experiment = Experiment(small_scenario, {"nominal": {}},
                            {"pfc": PredictorConfig(controller="pfc", pfc={"aliases": 0}, pfc_alphas=[0.9, 0.99],
                                                    data={"frames": 1024, "dither_nm": 5.0})},
                            EvaluationConfig(frames=500, settle_frames=100, psd_segment_frames=128),
                            log=lambda line: None)
    result = experiment.run()
    scan = result.classical_settings["nominal"]["pfc"]
    tried = [e["pfc.alpha"] for e in scan["scanned"]]
    assert tried[:2] == [0.9, 0.99]  # then past the edge while the best is there
    assert all(alpha_past_edge({e["pfc.alpha"]: e["median_rms_nm"] for e in scan["scanned"][:i]}, i - 2) == alpha
               for i, alpha in enumerate(tried[2:], start=2))
    assert alpha_past_edge({e["pfc.alpha"]: e["median_rms_nm"] for e in scan["scanned"]}, len(tried) - 2) is None
    assert scan["median_rms_nm"] == min(e["median_rms_nm"] for e in scan["scanned"] if e["median_rms_nm"])
    assert experiment.classical_models[("pfc", "nominal")].info["alpha"] == scan["pfc.alpha"]
    assert result.stability["nominal"]["pfc"]["stable"]


@pytest.mark.cli
def test_compare_refuses_a_pfc_alpha_it_cannot_run_in_one_line(tmp_path, cli_error):
    import json
    from pathlib import Path

    tiny = Path(__file__).parent / "conf" / "tiny_compare.yaml"
    cli_error(["compare", "--config", tiny, "--predictors",
               json.dumps({"pfc": {"controller": "pfc", "pfc_alphas": [0.99, 1.5]}}), "--out", tmp_path / "o"],
              "pfc_alphas=[0.99, 1.5] is invalid: 1.5 is not a number from 0.5 to below 1", tmp_path / "o")
