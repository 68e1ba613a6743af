"""``data.target: dm_fit`` (issue 30's anti-aliasing prediction): with a Shack-Hartmann, a simulator-truth predictor
learns from the measured histories to cancel the DM's fit of the true phase ``P F phi`` instead of the measured
``R S phi``; the default (``measured``) is what it always was, and the option is refused in one line where it means
nothing."""

from __future__ import annotations

import pytest
import torch

from eofnn.control.baselines import Integrator
from eofnn.data.config import DataConfig
from eofnn.data.history import HistorySpec
from eofnn.data.stream import SimulatedTelemetry
from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
from eofnn.evaluation.experiment import Experiment
from eofnn.sim.scenario import Scenario
from eofnn.training.fit import fit_predictor

GRID = {"diameter_m": 3.2, "n_across": 8, "obstruction": 0.0}
ATMOSPHERE = {"r0_m": 0.15, "layers": [{"wind_speed_mps": 10.0}], "screen_frames": 400}
FRAMES = 200


def _scenario(delay: float = 2, sensor: str = "shack_hartmann") -> Scenario:
    config = {"grid": GRID, "atmosphere": ATMOSPHERE, "plant": {"delay_frames": delay}}
    if sensor == "shack_hartmann":
        config["sensor"] = {"kind": "shack_hartmann", "detector": {"magnitude": 8.0}}
    return Scenario.from_dict(config)


def _sequence(scenario: Scenario, kind: str, target: str, controller=None):
    data = DataConfig(frames=FRAMES, val_frames=FRAMES, sequence_frames=FRAMES, seed=3, target=target)
    spec = HistorySpec.from_scenario(kind, 3, scenario)
    stream = SimulatedTelemetry(scenario, spec, FRAMES, "train", data, controller)
    return spec, stream.sequence(0)


def _truth(scenario: Scenario, key: str) -> torch.Tensor:
    """``fit = P F phi`` or ``sensed = R S phi`` of the first training sequence, straight from the sensor."""
    return scenario.turbulence(3, "train:0", 1).products(0, FRAMES)[key]


@pytest.mark.parametrize("delay", [2, 1.5])
def test_the_fit_target_is_minus_p_f_phi_at_the_frame_each_command_acts_and_the_inputs_stay_measured(delay):
    scenario = _scenario(delay)
    spec, (history, target) = _sequence(scenario, "open_loop", "dm_fit")
    _, (measured_history, measured_target) = _sequence(scenario, "open_loop", "measured")
    fit, sensed = _truth(scenario, "fit"), _truth(scenario, "sensed")
    first, f = spec.first_frame, spec.delay_fraction
    expected = -fit[:, first:] if not f else -((1 - f) * fit[:, first:-1] + f * fit[:, first + 1:])
    torch.testing.assert_close(target, expected, rtol=0, atol=1e-12)
    # The default target is the measured reconstruction, aliasing included: not the fit.
    expected_measured = -sensed[:, first:] if not f else -((1 - f) * sensed[:, first:-1] + f * sensed[:, first + 1:])
    torch.testing.assert_close(measured_target, expected_measured, rtol=0, atol=1e-12)
    assert (target - measured_target).abs().max() > 1.0  # nm: the aliasing the fit target leaves out
    # Inputs are the same noisy POL histories either way, and the newest tap is d frames behind the target.
    assert torch.equal(history, measured_history)
    newest = sensed[:, first - spec.whole_delay:][:, :history.shape[1]]
    gap = (history[..., 0] - newest).pow(2).mean().sqrt()
    assert 0.1 < gap < 0.2 * newest.pow(2).mean().sqrt()  # the sensor's photon noise, and nothing else, is added


def test_the_fit_target_holds_for_closed_loop_data_with_the_plants_dm_gain():
    scenario = _scenario().with_plant(dm_gain=1.25)
    spec, (history, target) = _sequence(scenario, "closed_loop", "dm_fit", Integrator(0.3))
    _, (measured_history, _) = _sequence(scenario, "closed_loop", "measured", Integrator(0.3))
    torch.testing.assert_close(target, -_truth(scenario, "fit")[:, spec.first_frame:] / 1.25, rtol=0, atol=1e-12)
    assert torch.equal(history, measured_history)


def test_the_default_is_the_measured_target():
    assert DataConfig().target == "measured"
    assert DataConfig().learns_from == "simulator truth"
    assert "DM's fit" in DataConfig(target="dm_fit").learns_from


@pytest.mark.parametrize(("build", "message"), [
    (lambda: DataConfig(target="fit"), "data.target='fit' is invalid: it must be one of measured, dm_fit"),
    (lambda: DataConfig(target="dm_fit", truth=False), "data.target='dm_fit' needs data.truth: true"),
    (lambda: PredictorConfig(data={"target": "dm_fit"}, optimization={"fit_method": "closed_loop"}),
     "data.target='dm_fit' is invalid with optimization.fit_method: closed_loop"),
    (lambda: _sequence(_scenario(sensor="subaperture"), "open_loop", "dm_fit"),
     "data.target='dm_fit' is for a Shack-Hartmann scenario"),
])
def test_where_the_fit_target_means_nothing_it_is_refused_in_one_line(build, message):
    with pytest.raises(ConfigError) as error:
        build()
    assert message in str(error.value) and "\n" not in str(error.value)


def test_a_checkpoint_says_which_target_it_learnt():
    data = DataConfig(frames=FRAMES, val_frames=FRAMES, sequence_frames=FRAMES, target="dm_fit")
    predictor = fit_predictor(_scenario(), "open_loop", 2, data=data).predictor
    assert predictor.info["data"]["target"] == "dm_fit"


@pytest.mark.parametrize("analytic", [True, False])
def test_analytic_stability_is_reported_by_default_and_can_be_skipped(small_scenario, analytic):
    predictors = {"integrator": PredictorConfig(controller="integrator", gain=0.4),
                  "extrapolator": PredictorConfig(controller="extrapolator", order=1)}
    evaluation = EvaluationConfig(frames=300, settle_frames=100, analytic_stability=analytic)
    result = Experiment(small_scenario, {"nominal": {}}, predictors, evaluation, log=lambda _: None).run().to_json()
    assert set(result["stability"].get("nominal", {})) == ({"integrator", "extrapolator"} if analytic else set())
    assert EvaluationConfig().analytic_stability is True
    with pytest.raises(ConfigError, match="evaluation.analytic_stability='no' is invalid"):
        EvaluationConfig(analytic_stability="no")


def test_a_shack_hartmann_run_splits_its_residual_by_spatial_frequency(tmp_path):
    """metrics.json's spatial_split_nm: the residual over the pupil inside the control circle, in the control
    square's corners and beyond it (the fitting error lies there), adding in quadrature to about the run's RMS;
    results.md tabulates it."""
    from eofnn.reporting.report import write_report

    evaluation = EvaluationConfig(frames=300, settle_frames=100, analytic_stability=False, error_budget=False)
    result = Experiment(_scenario(), {"nominal": {}}, {"integrator": PredictorConfig(controller="integrator", gain=0.4)},
                        evaluation, log=lambda _: None).run()
    metrics = result.metrics["nominal"]["integrator"]
    split = metrics.spatial_split_nm
    assert set(split) == {"inside_control_circle", "control_square_corners", "beyond_control"}
    assert split["beyond_control"] > 0.3 * metrics.median_rms_nm  # 8 across on 3.2 m: the fitting error is large
    assert sum(v * v for v in split.values()) ** 0.5 == pytest.approx(metrics.median_rms_nm, rel=0.25)
    assert result.to_json()["scenarios"]["nominal"]["integrator"]["spatial_split_nm"] == split
    write_report(result, tmp_path, 1000.0)
    assert "| integrator | " in (tmp_path / "results.md").read_text().split("Where the residual lies in nominal")[1]
