"""Never worse than the integrator (eofnn/evaluation/fallback.py, eofnn/control/fallback.py): a predictor guarded by
``fallback:`` is deployed only where it beats the best-gain integrator on a validation stream of its own."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from eofnn.analysis.block import CoupledAnalysisUnavailable
from eofnn.analysis.stability import LoopSetup, analyse, analyse_integrator
from eofnn.control.baselines import Integrator
from eofnn.control.config import FallbackConfig
from eofnn.control.fallback import ModalFallback
from eofnn.data.config import DataConfig
from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.evaluation.config import PredictorConfig
from eofnn.evaluation.fallback import FallbackDecision, decide_fallback, fallback_stability
from eofnn.models.linear import LinearFilter
from eofnn.sim.loop.runner import LoopInput
from eofnn.sim.scenario import Scenario
from eofnn.training.config import OptimizationConfig
from eofnn.training.fit import TrainedPredictor, fit_predictor

SMALL = FallbackConfig(per="mode", frames=400, settle_frames=80, realisations=2, blocks=2, gains=[0.5, 0.6])


def _integrator_filter(n_actuators: int, gain: float, structure: str = "shared",
                       dtype: torch.dtype = torch.float64) -> TrainedPredictor:
    """A closed-loop linear filter that is an integrator of ``gain``: ``y(n) = y(n-1) - gain wfs(n-2)``."""
    spec = HistorySpec("closed_loop", 1, 2)
    rows = 1 if structure == "shared" else n_actuators
    network = LinearFilter(n_actuators, spec.n_taps, structure).to(dtype)
    with torch.no_grad():
        network.weight.copy_(torch.tensor([[1.0, -gain]]).expand(rows, -1))
    return TrainedPredictor(network, spec, {}, n_actuators)


def _residual(scenario, controller, frames: int = 400) -> torch.Tensor:
    return scenario.median_residual_nm(controller, frames, 3, "fallback-test", 100)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])  # the filter's fast path, and its general one
def test_the_predictor_reads_back_the_composite_command_it_did_not_choose(small_scenario, dtype):
    """A filter that integrates with gain 0.6 on the modes B and the integrator of gain 0.2 elsewhere make the loop
    ``y(n) = y(n-1) - (0.6 P + 0.2 (I - P)) wfs(n-2)``, P = B Bᵀ, only if the filter's histories hold the command
    applied: its own would integrate 0.6 wfs on every mode."""
    k = small_scenario.grid.n_actuators
    basis = torch.linalg.qr(torch.randn(k, 10, generator=torch.Generator().manual_seed(0), dtype=torch.float64))[0]
    composite = ModalFallback(_integrator_filter(k, 0.6, dtype=dtype).controller(), 0.2, basis)
    projector = basis @ basis.T
    gain_matrix = 0.6 * projector + 0.2 * (torch.eye(k, dtype=torch.float64) - projector)

    class Reference:
        def reset(self, batch, n_actuators, delay_frames, dtype):
            self.y = torch.zeros(batch, n_actuators, dtype=dtype)

        def step(self, inp: LoopInput) -> torch.Tensor:
            self.y = self.y - inp.wfs @ gain_matrix
            return self.y

    expected, got = _residual(small_scenario, Reference()), _residual(small_scenario, composite)
    assert got == pytest.approx(expected, rel=1e-9 if dtype == torch.float64 else 1e-4)
    assert got != pytest.approx(_residual(small_scenario, Integrator(0.6)), rel=1e-3)


def test_all_modes_kept_is_the_predictor_and_none_is_the_integrator(small_scenario):
    k = small_scenario.grid.n_actuators
    predictor = _integrator_filter(k, 0.5, "per_actuator")
    everywhere = ModalFallback(predictor.controller(), 0.3, torch.ones(k, dtype=torch.bool))
    nowhere = ModalFallback(predictor.controller(), 0.3, torch.zeros(k, dtype=torch.bool))
    assert _residual(small_scenario, everywhere) == _residual(small_scenario, predictor.controller())
    assert _residual(small_scenario, nowhere) == _residual(small_scenario, Integrator(0.3))


@pytest.fixture(scope="module")
def noise_free_eof():
    """An open-loop EOF fitted without noise (ridge alpha 1e-9): it passes 20 nm of WFS noise back at full gain."""
    tiny = Scenario.from_yaml(Path(__file__).parent / "conf" / "tiny_scenario.yaml")
    scenario = replace(tiny, atmosphere=replace(tiny.atmosphere, screen_frames=800))  # short screens: fast streams
    data = DataConfig(frames=1500, val_frames=300, sequence_frames=750)
    return scenario, fit_predictor(scenario, "open_loop", 3, data=data,
                                   optimization=OptimizationConfig(alpha=1e-9)).predictor


def test_a_noise_free_predictor_in_a_noisy_loop_falls_back_and_is_no_worse_than_the_integrator(noise_free_eof):
    scenario, predictor = noise_free_eof
    noisy = scenario.with_plant(wfs_noise_nm=20.0)
    decision = decide_fallback(predictor.controller, SMALL, noisy)
    report = decision.report
    assert decision.deployed == "integrator" and report["predictor_modes"] == 0
    assert len(report["fallen_back"]["worse"]) > report["n_modes"] // 2  # most modes: the predictor is worse
    assert report["validation_median_rms_nm"]["predictor"] > 2 * report["validation_median_rms_nm"]["integrator"]
    guarded = _residual(noisy, decision.build(predictor.controller), 600)
    best_gain = _residual(noisy, Integrator(report["integrator_gain"]), 600)
    assert guarded == best_gain < _residual(noisy, predictor.controller(), 600)


def test_where_the_predictor_wins_it_is_kept(noise_free_eof):
    scenario, predictor = noise_free_eof
    decision = decide_fallback(predictor.controller, FallbackConfig(**{**vars(SMALL), "per": "whole"}), scenario)
    assert decision.deployed == "predictor", decision.report["why"]
    assert decision.report["whole"]["predictor"]["gain_nm2"] > 0
    assert _residual(scenario, decision.build(predictor.controller)) == _residual(scenario, predictor.controller())


def test_the_composite_has_analytic_margins_where_its_modes_decouple(small_scenario):
    """A shared filter on half the KL modes, the integrator on the rest: the stable DM-gain interval is the
    intersection of the two loops' intervals; a per-actuator filter on KL modes couples them: none, said so."""
    k = small_scenario.grid.n_actuators
    shared = _integrator_filter(k, 0.9)
    basis = torch.linalg.qr(torch.randn(k, k // 2, dtype=torch.float64))[0]
    decision = FallbackDecision("composite", 0.3, basis, {"modes": "kl"})
    config = PredictorConfig()
    result = fallback_stability(decision, config, shared, small_scenario)
    setup = LoopSetup.from_plant(small_scenario.plant, small_scenario.frame_rate_hz)
    own = analyse(shared.network.weight.detach(), "closed_loop", 1, setup, structure="shared").gain_margin
    integrator = analyse_integrator(0.3, 0.0, setup).gain_margin
    low, high = result.gain_margin
    assert high == pytest.approx(min(own[1], integrator[1])) and high == pytest.approx(own[1])
    assert math.isclose(low, max(own[0], integrator[0]), abs_tol=1e-12)
    with pytest.raises(CoupledAnalysisUnavailable, match="couples the modes"):
        fallback_stability(decision, config, _integrator_filter(k, 0.9, "per_actuator"), small_scenario)
    mask = torch.arange(k) < 3
    actuators = fallback_stability(FallbackDecision("composite", 0.3, mask, {"modes": "actuators"}), config,
                                   _integrator_filter(k, 0.9, "per_actuator"), small_scenario)
    assert actuators.gain_margin[1] == pytest.approx(own[1])


@pytest.mark.parametrize("fields, message", [
    ({"controller": "integrator", "fallback": {"per": "whole"}}, "may lose to the integrator, not 'integrator'"),
    ({"controller": "lqg", "fallback": {"per": "mode"}}, "needs controller: predictor without adaptation"),
    ({"fallback": {"per": "mode", "modes": "zernike"}}, "fallback.modes"),
    ({"fallback": {"per": "whole", "realisations": 1, "blocks": 1}}, "at least 2 blocks"),
    ({"fallback": {"per": "always"}}, "fallback.per"),
])
def test_a_fallback_that_cannot_run_is_refused_in_one_line(fields, message):
    with pytest.raises(ConfigError, match=message) as err:
        PredictorConfig(**fields)
    assert "\n" not in str(err.value)


def test_the_default_guards_nothing():
    assert not PredictorConfig().fallback.active


def test_a_guarded_copy_of_a_contender_is_trained_once_and_scores_what_a_separate_fit_would(small_scenario,
                                                                                            tmp_path):
    """Two contenders whose configs differ only in ``fallback`` share one training (its checkpoint written under both
    names); the guarded one's predictor is the very fit a run without its twin trains."""
    from eofnn.evaluation.config import EvaluationConfig
    from eofnn.evaluation.experiment import Experiment

    data = DataConfig(frames=600, val_frames=300, sequence_frames=600)
    plain = PredictorConfig(history_length=2, data=data)
    guarded = replace(plain, fallback=FallbackConfig(per="whole", gains=[0.3, 0.5], frames=300, realisations=1))
    evaluation = EvaluationConfig(frames=300, settle_frames=100, analytic_stability=False, error_budget=False)
    lines: list[str] = []
    both = Experiment(small_scenario, {"nominal": {}}, {"eof": plain, "eof_guarded": guarded}, evaluation,
                      checkpoint_dir=tmp_path, log=lines.append)
    result = both.run()
    alone = Experiment(small_scenario, {"nominal": {}}, {"eof_guarded": guarded}, evaluation, log=lambda _: None)
    assert sum(line.startswith("training ") for line in lines) == 1
    assert any("eof_guarded: trained as eof is" in line for line in lines)
    assert both.predictor("eof_guarded", "nominal") is both.predictor("eof", "nominal")
    torch.testing.assert_close(both.predictor("eof_guarded", "nominal").network.weight,
                               alone.predictor("eof_guarded", "nominal").network.weight, rtol=0, atol=0)
    assert (tmp_path / "eof_guarded__nominal.ckpt").read_bytes() == (tmp_path / "eof__nominal.ckpt").read_bytes()
    assert set(result.metrics["nominal"]) == {"eof", "eof_guarded"}
