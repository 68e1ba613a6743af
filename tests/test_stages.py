"""compare's stages (eofnn/evaluation/stages.py): the analyses are planned, and refused in one line, before the run."""

from __future__ import annotations

import pytest

from eofnn.errors import ConfigError
from eofnn.evaluation.stages import AnalysisPlan, add_simulated_margins, plan_analyses


def test_the_plan_resolves_pareto_and_checks_every_name():
    plan = plan_analyses(["nominal", "dm_gain_2"], robustness={"dm_gain": [0.5, 1.5]}, simulated_margins=["dm_gain_2"],
                         pareto=True)
    assert plan == AnalysisPlan(("dm_gain_2",), {"dm_gain": [0.5, 1.5]}, "nominal")
    assert plan_analyses(["nominal"]) == AnalysisPlan()
    assert plan_analyses(["a", "b"], pareto="b").pareto_scenario == "b"
    with pytest.raises(ConfigError, match="'windy' is not a scenario: allowed are nominal, dm_gain_2"):
        plan_analyses(["nominal", "dm_gain_2"], simulated_margins=["windy"])
    with pytest.raises(ConfigError, match="'other' is not a scenario"):
        plan_analyses(["nominal"], pareto="other")
    with pytest.raises(ConfigError, match="robustness="):
        plan_analyses(["nominal"], robustness={"dm_gain": [1.0], "delay_frames": [2], "wfs_noise_nm": [1.0]})


def test_margins_are_simulated_only_where_no_analytic_interval_exists(monkeypatch):
    """A network (no analytic interval) gets one by simulation; a linear controller, the uncorrected loop and the
    pseudo-integrator do not; the verdict is recomputed once, after them."""
    import eofnn.evaluation.margins as margins

    calls, verdicts = [], []
    monkeypatch.setattr(margins, "simulated_dm_gain_interval", lambda exp, name, scenario: calls.append(
        (name, scenario)) or {"dm_gain_interval": [0.1, 1.9]})

    class Experiment:
        predictors = {"uncorrected": None, "pseudo_integrator": None, "ol_eof": None, "mlp": None}

        def verdict(self, result):
            verdicts.append(dict(result.simulated_stability))
            return {"recomputed": True}

    class Result:
        stability = {"nominal": {"ol_eof": {}}}
        simulated_stability: dict = {}
        verdict = None

    result = Result()
    add_simulated_margins(Experiment(), result, ["nominal"], log=lambda _: None)
    assert calls == [("mlp", "nominal")]
    assert result.simulated_stability == {"nominal": {"mlp": {"dm_gain_interval": [0.1, 1.9]}}}
    assert result.verdict == {"recomputed": True} and len(verdicts) == 1
    result = Result()
    result.simulated_stability = {}
    add_simulated_margins(Experiment(), result, [], log=lambda _: None)
    assert result.verdict is None  # nothing simulated: the run's verdict stands
