"""Adding a sensor touches one room: a sensor defined in this file alone (a noiseless projection of the residual onto
half of the actuator space, registered by name) runs in all three drivers, the batched loop, the differentiable
rollout and the external-simulator driver, and they close the same loop with it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eofnn.control.baselines import Integrator
from eofnn.control.predictive import PredictiveController
from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.interop.loop import IntegratorControl, run_closed_loop
from eofnn.interop.native import NativeLoop
from eofnn.models.linear import LinearFilter
from eofnn.sim.loop.kernel import register_sensor
from eofnn.sim.loop.runner import run_loop
from eofnn.sim.scenario import Scenario
from eofnn.training.rollout import LoopWindow, rollout

SCENARIO = Scenario.from_dict({"grid": {"diameter_m": 2.0, "n_across": 10},
                               "atmosphere": {"r0_m": 0.15, "layers": [{"wind_speed_mps": 10.0}],
                                              "screen_frames": 400}})


class ProjectionMeasurement:
    """``wfs = B B^T eps``: what the sensor sees of the residual, noiseless."""

    noise_size, noisy = 0, False

    def __init__(self, basis: torch.Tensor) -> None:
        self.projector = basis @ basis.T

    def reset(self) -> None:
        pass

    def noise(self, unit):
        raise AssertionError("a noiseless sensor draws no noise")

    def measure(self, s, eps, dm, y, noise):
        return eps @ self.projector

    def to(self, device):
        self.projector = self.projector.to(device)
        return self


@register_sensor("test_projection")
class ProjectionSensor:
    """A noiseless sensor that sees the residual projected on half of the actuator space (a fixed random basis)."""

    def __init__(self, grid) -> None:
        k = grid.n_actuators
        gaussian = torch.randn(k, k // 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        self.basis = torch.linalg.qr(gaussian)[0]

    def measurement(self, plant, dm_gain=None, wfs_gain=None) -> ProjectionMeasurement:
        return ProjectionMeasurement(self.basis)


def test_the_batched_loop_runs_the_sensor_by_name():
    turbulence = SCENARIO.turbulence(3, "test", 1)
    seen = run_loop(turbulence, SCENARIO.plant, Integrator(0.4), 300, sensor="test_projection", progress=False)
    zonal = run_loop(turbulence, SCENARIO.plant, Integrator(0.4), 300, progress=False)
    basis = ProjectionSensor(SCENARIO.grid).basis
    wfs = seen.telemetry.wfs[0]
    torch.testing.assert_close(wfs @ basis @ basis.T, wfs, rtol=0, atol=1e-9)  # it reports only what it sees
    # Half of the residual is never measured, so never corrected: the loop leaves far more than the zonal sensor's.
    assert float(seen.residual_rms_nm[0, 100:].median()) > 1.5 * float(zonal.residual_rms_nm[0, 100:].median())


def test_the_rollout_and_the_external_driver_close_the_same_loop_with_it():
    turbulence = SCENARIO.turbulence(3, "test", 1)
    n_frames, k = 300, SCENARIO.grid.n_actuators
    batched = run_loop(turbulence, SCENARIO.plant, Integrator(0.4), n_frames, sensor="test_projection",
                       record=("eps",), progress=False)
    # The external-simulator driver over eofnn's own physics, with the numpy integrator and with eofnn's own.
    for controller in (IntegratorControl(0.4), Integrator(0.4)):
        external = run_closed_loop(NativeLoop(SCENARIO, "test_projection"), controller, n_frames, 3)
        assert external.diverged_frame is None
        np.testing.assert_allclose(external.residual_rms_nm, batched.residual_rms_nm[0].numpy(), rtol=1e-12)
    # The differentiable rollout: an integrator as a closed-loop filter, y(n) = y(n - 1) - 0.4 wfs(n - 2).
    spec = HistorySpec.from_scenario("closed_loop", 1, SCENARIO)
    net = LinearFilter(k, spec.n_taps)
    with torch.no_grad():
        net.weight.copy_(torch.tensor([[1.0, -0.4]], dtype=torch.float64).expand(k, 2))
    window = LoopWindow(turbulence.frames(0, n_frames), None, SCENARIO.plant, SCENARIO.grid, 0,
                        sensor="test_projection")
    with torch.no_grad():
        eps = rollout(net, spec, window)
    looped = run_loop(turbulence, SCENARIO.plant, PredictiveController(net, spec), n_frames, sensor="test_projection",
                      record=("eps",), progress=False)
    assert (eps - looped.telemetry.eps).abs().max() <= 1e-9 * looped.telemetry.eps.abs().max()
    # The filter is the integrator once its history is full (frame 1 on): the loop the other drivers closed, to a
    # first command that differs.
    assert float(looped.residual_rms_nm[0, 100:].median()) == pytest.approx(
        float(batched.residual_rms_nm[0, 100:].median()), rel=1e-3)


def test_an_unknown_sensor_is_one_line():
    with pytest.raises(ConfigError, match="sensor='nope' is invalid: registered sensors are .*subaperture"):
        run_loop(SCENARIO.turbulence(3, "test", 1), SCENARIO.plant, Integrator(0.4), 10, sensor="nope")


def _scenario_yaml(tmp_path, kind: str):
    path = tmp_path / f"{kind}.yaml"
    path.write_text("grid: {diameter_m: 2.0, n_across: 10}\n"
                    "atmosphere: {r0_m: 0.15, layers: [{wind_speed_mps: 10.0}], screen_frames: 400}\n"
                    f"sensor: {{kind: {kind}}}\n")
    return path


@pytest.mark.cli
def test_a_compare_runs_the_sensor_its_yaml_names(cli, tmp_path):
    import json

    config = tmp_path / "compare.yaml"
    config.write_text(f"scenario: {_scenario_yaml(tmp_path, 'test_projection')}\nscenarios: {{nominal: {{}}}}\n"
                      "predictors: {integrator: {controller: integrator, gain: 0.4}}\n"
                      "evaluation: {frames: 300, settle_frames: 100, realisations: 1, seed: 3, "
                      "analytic_stability: false}\n")
    code, err = cli("compare", "--config", config, "--out", tmp_path / "out")
    assert code == 0, err
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    got = metrics["scenarios"]["nominal"]["integrator"]["median_rms_nm"]
    scenario = Scenario.from_yaml(_scenario_yaml(tmp_path, "test_projection"))
    assert scenario.sensor.registered == "test_projection"
    # The loop compare closed is the batched loop with that sensor, and not the zonal sensor's.
    seen = run_loop(SCENARIO.turbulence(3, "test", 1), SCENARIO.plant, Integrator(0.4), 300, noise_seed=3,
                    sensor="test_projection", progress=False)
    zonal = run_loop(SCENARIO.turbulence(3, "test", 1), SCENARIO.plant, Integrator(0.4), 300, noise_seed=3,
                     progress=False)
    assert got == pytest.approx(float(torch.quantile(seen.residual_rms_nm[0, 100:], 0.5)), rel=1e-9)
    assert got > 1.5 * float(zonal.residual_rms_nm[0, 100:].median())
    # The external-simulator driver takes the scenario's sensor too.
    external = run_closed_loop(NativeLoop(scenario), IntegratorControl(0.4), 300, 3)
    np.testing.assert_allclose(external.residual_rms_nm, seen.residual_rms_nm[0].numpy(), rtol=1e-12)


@pytest.mark.cli
def test_an_unknown_sensor_kind_is_one_line_naming_the_allowed_kinds(cli, tmp_path):
    with pytest.raises(ConfigError, match=r"^sensor.kind='nope' is invalid: it must be one of subaperture, "
                                          r"shack_hartmann, .*test_projection"):
        Scenario.from_yaml(_scenario_yaml(tmp_path, "nope"))
    code, err = cli("simulate", "--scenario", _scenario_yaml(tmp_path, "nope"), "--predictor.controller",
                    "integrator", "--frames", "10", "--out", tmp_path / "t.npz")
    assert code == 2
    assert err.strip().splitlines()[-1].startswith("eofnn: error: ") and "sensor.kind='nope'" in err, err
    assert "Traceback" not in err and "test_projection" in err
    with pytest.raises(ConfigError, match="sensor.detector=.* is invalid for sensor kind 'test_projection'"):
        Scenario.from_dict({"sensor": {"kind": "test_projection", "detector": {"magnitude": 8}}})


def test_open_loop_training_data_is_what_the_named_sensor_measures(tmp_path):
    from eofnn.data.config import DataConfig
    from eofnn.data.stream import SimulatedTelemetry

    scenario = Scenario.from_yaml(_scenario_yaml(tmp_path, "test_projection"))
    spec = HistorySpec.from_scenario("open_loop", 2, scenario)
    arrays = SimulatedTelemetry(scenario, spec, 300, data=DataConfig(seed=1, sequence_frames=300)).telemetry(0)
    basis = ProjectionSensor(scenario.grid).basis
    torch.testing.assert_close(arrays["s_hat"], arrays["s"] @ basis @ basis.T, rtol=0, atol=1e-9)
