"""The tuned extrapolator: its order (and least-squares smoothing) chosen per scenario on a stream of its own, like the
best-gain integrator's gain; the weights of a smoothed extrapolation; bad scan settings in one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from eofnn.control.classical import Extrapolator, extrapolation_weights, extrapolator_filter
from eofnn.data.history import blended_target, open_loop_history
from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
from eofnn.evaluation.contenders import SCAN_STREAM
from eofnn.evaluation.experiment import Experiment
from eofnn.evaluation.results import ExperimentResult, describe_setting_scan
from eofnn.sim.scenario import Scenario

F64 = torch.float64
TINY_COMPARE = Path(__file__).parent / "conf" / "tiny_compare.yaml"


# -- the smoothed extrapolation ----------------------------------------------------------------------------------
@pytest.mark.parametrize("delay", [2, 1.5])
@pytest.mark.parametrize("order, smoothing", [(0, 3), (1, 2), (2, 4)])
def test_a_smoothed_extrapolation_is_still_exact_on_polynomials_of_its_order(order, smoothing, delay):
    n = torch.arange(40, dtype=F64)
    coefficients = (2.5, -0.5, 0.25)[: order + 1]  # a polynomial of degree ``order``
    s = sum(c * n**k for k, c in enumerate(coefficients)).unsqueeze(-1)
    network, spec = extrapolator_filter(order, delay, smoothing=smoothing)
    assert spec.history_length == order + 1 + smoothing
    prediction = -network(open_loop_history(s, spec))
    torch.testing.assert_close(prediction, blended_target(s, spec), rtol=0, atol=1e-9)


def test_smoothing_averages_the_noise_down_and_zero_is_the_interpolation_of_before():
    # Order 1 at a two-frame delay, fitted to 4 POL values: the least-squares line, noise gain 1.64 against 3.61.
    torch.testing.assert_close(extrapolation_weights(1, 2, smoothing=2),
                               torch.tensor([1.3, 0.6, -0.1, -0.8], dtype=F64), rtol=0, atol=1e-12)
    assert float(extrapolation_weights(1, 2, 2).norm()) < 0.5 * float(extrapolation_weights(1, 2).norm())
    # Order 0 over 4 values is their mean; smoothing 0 keeps the Lagrange weights bit for bit.
    torch.testing.assert_close(extrapolation_weights(0, 2, 3), torch.full((4,), 0.25, dtype=F64))
    assert torch.equal(extrapolation_weights(2, 2, 0), torch.tensor([6.0, -8.0, 3.0], dtype=F64))


# -- the scan, on a stream of its own ----------------------------------------------------------------------------
def _fake_residuals(monkeypatch, residual_of) -> list[tuple]:
    """Replace the closed loop of every scan by ``residual_of(order, smoothing)``; the calls' (seed, stream) go to the
    returned list."""
    calls: list[tuple] = []

    def fake(self, controller, n_frames, seed, stream, settle_frames, **kwargs):
        assert isinstance(controller, Extrapolator)
        calls.append((seed, stream, n_frames))
        return residual_of(controller.order, controller.smoothing)

    monkeypatch.setattr(Scenario, "median_residual_nm", fake)
    return calls


def test_the_scan_keeps_the_lowest_residual_of_its_own_stream_never_the_tests(small_scenario, monkeypatch):
    residuals = {(0, 0): 9.0, (1, 0): 4.0, (2, 0): 2.0, (0, 2): 8.0, (1, 2): 3.0, (2, 2): None}  # (2, 2) diverged
    calls = _fake_residuals(monkeypatch, lambda order, smoothing: residuals[(order, smoothing)])
    cfg = PredictorConfig(controller="extrapolator", orders=[0, 1, 2], smoothings=[0, 2],
                          data={"frames": 500, "seed": 7})
    lines: list[str] = []
    experiment = Experiment(small_scenario, {"nominal": {}}, {"extrap": cfg},
                            EvaluationConfig(frames=600, settle_frames=100, seed=1), log=lines.append)
    chosen = experiment.config("extrap", "nominal")
    assert (chosen.order, chosen.smoothing, chosen.orders, chosen.smoothings) == (2, 0, None, None)
    # Every setting ran once, all on the scan stream of the scan's own seed: the test stream (seed 1) is never used.
    assert calls == [(7, SCAN_STREAM, 500)] * 6 and SCAN_STREAM != "test"
    scan = experiment.setting_scans[("extrap", "nominal")]
    assert scan["median_rms_nm"] == 2.0 and len(scan["scanned"]) == 6
    assert lines[-1].endswith("extrap: order 2, smoothing 0 chosen (2 nm) over order 1, smoothing 2 (3), order 1, "
                              "smoothing 0 (4), order 0, smoothing 2 (8), order 0, smoothing 0 (9), order 2, "
                              "smoothing 2 (diverged) on a stream of its own")
    experiment.config("extrap", "nominal")
    assert len(calls) == 6  # scanned once per scenario, then reused


def test_an_extrapolator_whose_every_order_diverges_is_one_line(small_scenario, monkeypatch):
    _fake_residuals(monkeypatch, lambda order, smoothing: None)
    experiment = Experiment(small_scenario, {"nominal": {}},
                            {"extrap": PredictorConfig(controller="extrapolator", orders=[1, 2], data={"frames": 500})},
                            EvaluationConfig(frames=600, settle_frames=100), log=lambda line: None)
    with pytest.raises(ConfigError, match=r"every setting of controller extrapolator \(orders=\[1, 2\]\) diverged"):
        experiment.config("extrap", "nominal")


def test_results_md_names_the_order_chosen_over_the_others():
    scan = {"order": 2, "smoothing": 0, "median_rms_nm": 2.06,
            "scanned": [{"order": 0, "smoothing": 0, "median_rms_nm": 23.0},
                        {"order": 1, "smoothing": 0, "median_rms_nm": 3.86},
                        {"order": 2, "smoothing": 0, "median_rms_nm": 2.06}]}
    assert describe_setting_scan(scan) == "order 2 chosen (2.06 nm) over order 1 (3.86), order 0 (23)"
    result = ExperimentResult({}, classical_settings={"noise_0": {"extrapolator": scan}})
    assert result.to_json()["classical_settings"]["noise_0"]["extrapolator"]["order"] == 2


@pytest.mark.cli
@pytest.mark.slow
def test_compare_chooses_order_2_without_noise_and_a_lower_order_with_much(tmp_path, cli):
    """The real loops (tiny scenario): at noise 0 the quadratic extrapolation wins; at 30 nm of WFS noise it amplifies
    the noise tenfold and order 0 or 1 wins. metrics.json and results.md say which."""
    predictors = {"extrapolator": {"controller": "extrapolator", "orders": [0, 1, 2], "data": {"frames": 300}}}
    code, err = cli("compare", "--config", TINY_COMPARE, "--scenarios",
                    json.dumps({"noise_0": {}, "noise_30": {"wfs_noise_nm": 30.0}}), "--predictors",
                    json.dumps(predictors), "--evaluation.frames", "300", "--evaluation.settle_frames", "60",
                    "--evaluation.psd_segment_frames", "128", "--out", tmp_path / "out")
    assert code == 0, err
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    quiet, noisy = (metrics["classical_settings"][s]["extrapolator"] for s in ("noise_0", "noise_30"))
    assert quiet["order"] == 2 and noisy["order"] in (0, 1), (quiet, noisy)
    for scan in (quiet, noisy):
        finite = [e for e in scan["scanned"] if e["median_rms_nm"] is not None]
        assert [e["order"] for e in scan["scanned"]] == [0, 1, 2]
        assert scan["median_rms_nm"] == min(e["median_rms_nm"] for e in finite)
    text = (tmp_path / "out" / "results.md").read_text()
    assert f"- extrapolator in noise_0: {describe_setting_scan(quiet)}" in text
    assert f"- extrapolator in noise_30: order {noisy['order']} chosen" in text


@pytest.mark.parametrize("config, expected", [
    ({"controller": "extrapolator", "orders": [3]}, "orders=[3] is invalid: 3 is not one of 0, 1, 2"),
    ({"controller": "extrapolator", "orders": []}, "orders=[] is invalid: give a non-empty list"),
    ({"controller": "extrapolator", "orders": [1], "smoothings": [-1]}, "smoothings=[-1] is invalid: -1 is not an "
                                                                         "integer from 0 to 16"),
    ({"controller": "extrapolator", "smoothing": 1.5}, "smoothing=1.5 is invalid"),
    ({"controller": "integrator", "orders": [1, 2]}, "orders=[1, 2] is for controller: extrapolator, not "
                                                      "'integrator'"),
])
def test_bad_scan_settings_are_one_line_errors(config, expected):
    with pytest.raises(ConfigError) as err:
        PredictorConfig(**config)
    assert expected in str(err.value) and "\n" not in str(err.value)


@pytest.mark.cli
def test_compare_refuses_an_order_it_cannot_extrapolate_with_in_one_line(tmp_path, cli_error):
    cli_error(["compare", "--config", TINY_COMPARE, "--predictors",
               json.dumps({"extrapolator": {"controller": "extrapolator", "orders": [3]}}), "--out", tmp_path / "o"],
              "orders=[3] is invalid: 3 is not one of 0, 1, 2", tmp_path / "o")


@pytest.mark.cli
def test_the_fair_contest_asks_for_the_tuned_extrapolator(capsys):
    """configs/realistic_study.yaml parses; its extrapolator scans orders 0, 1, 2 (and smoothing), its LQG AR(1) and
    AR(2)."""
    import yaml

    from eofnn.cli.main import main

    path = Path(__file__).parent.parent / "configs" / "realistic_study.yaml"
    with pytest.raises(SystemExit) as info:
        main(["compare", "--config", str(path), "--out", "unused", "--print_config"])
    assert info.value.code == 0
    predictors = yaml.safe_load(capsys.readouterr().out)["predictors"]
    extrapolator = predictors["extrapolator"]
    assert predictors["lqg"]["ar_orders"] == [0, 1, 2]
    cfg = PredictorConfig(**{k: extrapolator[k] for k in ("controller", "orders", "smoothings", "data")})
    assert cfg.orders == [0, 1, 2] and {s["order"] for s in cfg.extrapolator_grid} == {0, 1, 2}
