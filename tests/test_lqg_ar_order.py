"""The LQG's AR order: AR(1) fitted in the AR(2) state space, and AR(1) against AR(2) chosen per scenario on a stream
of its own, like the best-gain integrator's gain; bad values in one line."""

from __future__ import annotations

import pytest
import torch

from eofnn.control.kalman import fit_ar, fit_ar1, fit_ar2
from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
from eofnn.evaluation.contenders import SCAN_STREAM
from eofnn.evaluation.experiment import Experiment
from eofnn.evaluation.results import describe_setting_scan
from eofnn.sim.scenario import Scenario

F64 = torch.float64


def test_ar1_recovers_an_ar1_process_with_its_noise_removed():
    a, q, noise = (torch.tensor(v, dtype=F64) for v in ([0.9, -0.5, 0.99], [1.0, 2.0, 0.1], [0.3, 0.0, 0.1]))
    c0 = q / (1 - a**2)
    autocovariance = torch.stack([c0 + noise, a * c0, a**2 * c0], 1)
    ar, q_hat = fit_ar1(autocovariance, noise)
    torch.testing.assert_close(ar, torch.stack([a, torch.zeros(3, dtype=F64)], 1))
    torch.testing.assert_close(q_hat, q)
    # AR(2) on the same process finds a2 = 0 too; fit_ar dispatches; a mode without turbulence is left alone.
    torch.testing.assert_close(fit_ar2(autocovariance, noise)[0][:, 1], torch.zeros(3, dtype=F64),
                               atol=1e-9, rtol=0)
    assert torch.equal(fit_ar(1, autocovariance, noise)[0], ar)
    flat = torch.tensor([[1.0, 0.0, 0.0]], dtype=F64)
    assert fit_ar1(flat, torch.tensor([1.0], dtype=F64))[0].abs().max() == 0


def test_the_ar_order_scan_keeps_the_lowest_residual_on_its_own_stream(small_scenario, monkeypatch):
    """Every AR order is built (from the same telemetry) and closes the loop on the scan stream; the faked residuals
    make AR(1) win, and the model that runs is the AR(1) one."""
    built: list[int] = []
    calls: list[tuple] = []

    def fake_build(config, scenario):
        from eofnn.control.classical import ModalLQG

        built.append(config.ar_order)
        k = scenario.grid.n_actuators
        ar = torch.tensor([[0.9, 0.0 if config.ar_order == 1 else 0.05]], dtype=F64).expand(k, 2)
        return ModalLQG(torch.eye(k, dtype=F64), ar, torch.ones(k, dtype=F64), torch.ones(k, dtype=F64),
                        torch.full((k, 2), 0.5, dtype=F64), 2, info={"ar": config.ar_order})

    def fake_residual(self, controller, n_frames, seed, stream, settle_frames, **kwargs):
        calls.append((seed, stream))
        return 3.0 if float(controller.ar[0, 1]) == 0 else 4.0

    monkeypatch.setitem(__import__("eofnn.control.registry", fromlist=["FROM_TELEMETRY"]).FROM_TELEMETRY, "lqg",
                        fake_build)
    monkeypatch.setattr(Scenario, "median_residual_nm", fake_residual)
    experiment = Experiment(small_scenario, {"nominal": {}},
                            {"lqg": PredictorConfig(controller="lqg", ar_orders=[2, 1],
                                                    data={"frames": 1024, "seed": 5, "dither_nm": 5.0})},
                            EvaluationConfig(frames=600, settle_frames=100, seed=1), log=lambda line: None)
    assert experiment.config("lqg", "nominal").ar_order == 1
    assert built == [2, 1] and calls == [(5, SCAN_STREAM)] * 2
    assert experiment.predictor_if_any("lqg", "nominal").info == {"ar": 1}  # the chosen model, not rebuilt
    assert built == [2, 1]
    scan = experiment.setting_scans[("lqg", "nominal")]
    assert describe_setting_scan(scan) == "AR(1) chosen (3 nm) over AR(2) (4)"


@pytest.mark.slow
def test_compare_builds_and_runs_the_lqg_of_the_chosen_ar_order(small_scenario):
    experiment = Experiment(small_scenario, {"nominal": {}},
                            {"lqg": PredictorConfig(controller="lqg", modes=10, ar_orders=[1, 2],
                                                    data={"frames": 1024, "dither_nm": 5.0})},
                            EvaluationConfig(frames=500, settle_frames=100, psd_segment_frames=128),
                            log=lambda line: None)
    result = experiment.run()
    scan = result.classical_settings["nominal"]["lqg"]
    assert [e["ar_order"] for e in scan["scanned"]] == [1, 2]
    assert scan["median_rms_nm"] == min(e["median_rms_nm"] for e in scan["scanned"] if e["median_rms_nm"])
    model = experiment.classical_models[("lqg", "nominal")]
    assert (model.ar[:, 1] == 0).all() == (scan["ar_order"] == 1)
    assert result.stability["nominal"]["lqg"]["stable"]


@pytest.mark.parametrize("config, expected", [
    ({"controller": "lqg", "ar_orders": [3]}, "ar_orders=[3] is invalid: 3 is not one of 0, 1, 2"),
    ({"controller": "lqg", "ar_orders": []}, "ar_orders=[] is invalid: give a non-empty list"),
    ({"controller": "lqg", "ar_order": 3}, "ar_order=3 is invalid"),
    ({"controller": "extrapolator", "ar_orders": [1]}, "ar_orders=[1] is for controller: lqg, not 'extrapolator'"),
])
def test_bad_ar_orders_are_one_line_errors(config, expected):
    with pytest.raises(ConfigError) as err:
        PredictorConfig(**config)
    assert expected in str(err.value) and "\n" not in str(err.value)
