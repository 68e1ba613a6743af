"""The best-gain integrator: compare chooses each scenario's gain on a stream of its own."""

from __future__ import annotations

from pathlib import Path

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


TINY_EVALUATE = Path(__file__).parent / "conf" / "tiny_evaluate.yaml"


@pytest.mark.slow
def test_evaluate_states_its_integrators_gain_and_runs_the_best_gain_scan_when_asked(small_scenario, tmp_path,
                                                                                     monkeypatch):
    """The fixed gain (0.5 unless set) and a scan's choice: in metrics.json, results.md and the progress line."""
    import json

    from eofnn.cli.compare import EvaluateConfig, evaluate

    lines: list[str] = []
    common = dict(scenario=small_scenario, checkpoints={}, baselines=["integrator"],
                  evaluation=EvaluationConfig(frames=400, settle_frames=100, psd_segment_frames=128), progress=False)
    monkeypatch.setattr("eofnn.cli.compare.log", lines.append)
    for out, integrator in [("fixed", PredictorConfig(controller="integrator")),
                            ("scan", {"gains": [0.3, 0.6], "refine_rounds": 0, "data": {"frames": 400}})]:
        evaluate(EvaluateConfig(out=str(tmp_path / out), integrator=integrator, **common))
    fixed = json.loads((tmp_path / "fixed" / "metrics.json").read_text())
    assert fixed["integrator_gain_used"] == {"nominal": {"integrator": {"gain": 0.5, "scanned": False}}}
    assert fixed["integrator_gains"] == {}
    assert "- integrator: gain 0.5 in nominal" in (tmp_path / "fixed" / "results.md").read_text()
    scan = json.loads((tmp_path / "scan" / "metrics.json").read_text())
    chosen = scan["integrator_gains"]["nominal"]["integrator"]
    assert set(chosen["scanned"]) == {"0.3", "0.6"}
    assert scan["integrator_gain_used"] == {"nominal": {"integrator": {"gain": chosen["gain"], "scanned": True}}}
    assert "Integrators at a fixed gain" not in (tmp_path / "scan" / "results.md").read_text()
    said = [line for line in lines if "integrator: median RMS" in line]
    assert said[0].endswith("; gain 0.5 (fixed, not tuned)") and said[1].endswith(
        f"; gain {chosen['gain']:g} (best of the scan)"), lines


@pytest.mark.cli
def test_evaluate_takes_the_integrators_settings_from_the_command_line_or_a_config(tmp_path, cli_error):
    from eofnn.cli.commands import parse

    args = ["evaluate", "--config", str(TINY_EVALUATE), "--checkpoints", "{}", "--out", str(tmp_path / "o")]
    default = parse(args).config.integrator
    assert default.controller == "integrator" and default.gain == 0.5 and default.gains is None
    scan = parse([*args, "--integrator.gains", "[0.3, 0.6]", "--integrator.data.frames", "600"]).config.integrator
    assert scan.controller == "integrator" and scan.gains == [0.3, 0.6] and scan.data.frames == 600
    config = tmp_path / "mine.yaml"
    config.write_text(TINY_EVALUATE.read_text().replace("scenario: tiny_scenario.yaml",
                                                        f"scenario: {TINY_EVALUATE.parent / 'tiny_scenario.yaml'}")
                      + "integrator: {gains: [0.2, 0.4], data: {frames: 500}}\n")
    from_file = parse(["evaluate", "--config", str(config), "--checkpoints", "{}", "--out", str(tmp_path / "o")])
    assert from_file.config.integrator.gains == [0.2, 0.4] and from_file.config.integrator.controller == "integrator"
    # Settings that would be silently unused, or another controller in the integrator's place: refused.
    cli_error([*args, "--baselines", "[pseudo_integrator]", "--integrator.gains", "[0.3]"],
              "integrator is set but baselines=['pseudo_integrator'] has no integrator", tmp_path / "o")
    cli_error([*args, "--integrator.controller", "lqg"], "integrator.controller='lqg' is invalid: it must be "
              "integrator", tmp_path / "o")
