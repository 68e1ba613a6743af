"""Training and replay from telemetry alone, against their simulator-truth counterparts in closed loop."""

from __future__ import annotations

import json

import pytest
import torch

from eofnn.control import Dithered, Integrator, PredictiveController
from eofnn.data.history import HistorySpec, build_history, targets
from eofnn.data.stream import DataConfig
from eofnn.data.targets import TelemetryBatches
from eofnn.errors import ConfigError, TelemetryError
from eofnn.evaluation.replay import replay
from eofnn.models.linear import LinearFilter
from eofnn.reporting.replay import replay_figure
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Telemetry, run_loop
from eofnn.sim.loop.plant import Plant
from eofnn.sim.scenario import Scenario
from eofnn.training.checkpoint import load_predictor
from eofnn.training.fit import FitOutput
from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_scenario_telemetry, fit_from_telemetry
from eofnn.training.identify import identify_plant
from eofnn.training.ridge import NormalEquations
from eofnn.training.task import OptimizationConfig

SPEC = {"open_loop": HistorySpec("open_loop", 4, 2), "closed_loop": HistorySpec("closed_loop", 4, 2)}


def scenario(**model_errors) -> Scenario:
    """10 actuators across a 2 m pupil (76 active), one 10 m/s layer, 1 kHz, two-frame delay."""
    atmosphere = Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=(Layer(1.0, 10.0, 0.0),))
    return Scenario(ActuatorGrid(2.0, 10), atmosphere, 1000.0, Plant(delay_frames=2, **model_errors))


def record(sc: Scenario, stream: str, frames: int, controller=None, seed: int = 1) -> Telemetry:
    controller = controller or Integrator(0.3)
    result = run_loop(sc.turbulence(0, stream), sc.plant, Dithered(controller, 10.0, seed=seed), frames,
                      noise_seed=seed + 1)
    assert not result.diverged
    return result.telemetry.realisation(0)


def closed_loop_rms(sc: Scenario, controller, frames: int = 3000) -> float:
    result = run_loop(sc.turbulence(0, "test"), sc.plant, controller, frames, noise_seed=7)
    return float("inf") if result.diverged else float(result.residual_rms_nm[:, 200:].median())


def truth_fit(tel: Telemetry, spec: HistorySpec, dm_gain: float, wfs_noise_nm: float = 2.0) -> LinearFilter:
    """The simulator-truth fit on the same recording, targets -s/g: closed loop from the recorded y, wfs; open loop
    from the true POL values plus the scenario's WFS noise, as :class:`eofnn.data.stream.SimulatedTelemetry` does."""
    net = LinearFilter(tel.y.shape[-1], spec.n_taps)
    if spec.kind == "open_loop":
        noise = torch.randn(tel.s.shape, generator=torch.Generator().manual_seed(11), dtype=torch.float64)
        history = build_history(spec, s=tel.s + wfs_noise_nm * noise)
    else:
        history = build_history(spec, y=tel.y, wfs=tel.wfs)
    ne = NormalEquations()
    ne.update(net.features(history), net.group_targets(targets(tel.s, spec, dm_gain)))
    net.load_solution(ne.solve(1e-9).weights)
    return net


@pytest.fixture(scope="module")
def unknown_plant():
    """DM gain 2 and a 0.2-pitch misregistration the learner is not told, 2 nm of WFS noise."""
    sc = scenario(dm_gain=2.0, misregistration_x=0.2, wfs_noise_nm=2.0)
    tel = record(sc, "train", 4000)
    return sc, tel, identify_plant(tel)


@pytest.mark.slow
def test_closed_loop_eof_from_telemetry_matches_truth(unknown_plant):
    sc, tel, plant = unknown_plant
    spec = SPEC["closed_loop"]
    fitted = fit_from_telemetry(tel, spec, plant=plant)
    assert fitted.info["plant_source"] == "identified" and fitted.predictor.dm_gain_model == pytest.approx(2.0, rel=0.02)
    from_telemetry = closed_loop_rms(sc, fitted.controller())
    from_truth = closed_loop_rms(sc, PredictiveController(truth_fit(tel, spec, 2.0), spec))
    assert from_telemetry == pytest.approx(from_truth, rel=0.2)


@pytest.mark.slow
def test_open_loop_eof_needs_the_identified_plant(unknown_plant):
    sc, tel, plant = unknown_plant
    spec = SPEC["open_loop"]
    identified = closed_loop_rms(sc, fit_from_telemetry(tel, spec, plant=plant).controller())
    truth = closed_loop_rms(sc, PredictiveController(truth_fit(tel, spec, 2.0), spec, dm_gain_model=2.0))
    nominal = closed_loop_rms(sc, fit_from_telemetry(tel, spec, plant=None).controller())
    integrator = closed_loop_rms(sc, Integrator(0.3))
    assert identified == pytest.approx(truth, rel=0.2)
    assert identified < 0.5 * integrator
    # The study's failure: POL under the nominal assumption loses most of the gain (worse than the integrator).
    assert nominal > 3 * identified and nominal > integrator


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["open_loop", "closed_loop"])
def test_replay_agrees_with_closed_loop(kind, tmp_path):
    """Replayed error (noise removed in quadrature) against the closed-loop residual of the same filter.

    An open-loop filter is replayed on held-out integrator telemetry; a closed-loop filter on telemetry it recorded
    itself (its history holds its own commands).
    """
    sc = scenario(dm_gain=2.0, wfs_noise_nm=2.0)
    train = record(sc, "train", 4000)
    plant = identify_plant(train)
    spec = SPEC[kind]
    fitted = fit_from_telemetry(train, spec, plant=plant)
    recorder = fitted.controller() if kind == "closed_loop" else Integrator(0.3)
    held_out = record(sc, "held-out", 3000, recorder, seed=3)
    result = replay(fitted.network, spec, held_out, plant=plant, settle_frames=100)
    in_loop = closed_loop_rms(sc, fitted.controller())
    assert result.predictor.median_rms_noise_corrected_nm == pytest.approx(in_loop, rel=0.2)
    assert result.predictor.median_rms_nm > result.predictor.median_rms_noise_corrected_nm
    assert result.own_controller.median_rms_nm > 2 * result.predictor.median_rms_nm or kind == "closed_loop"
    summary = json.loads(result.to_json(tmp_path / "replay.json"))
    assert len(summary["predictor"]["map_rms_nm"]) == sc.grid.n_actuators
    assert len(summary["psd_freq_hz"]) == len(summary["predictor"]["psd_nm2_per_hz"]) > 10
    assert replay_figure(result, tmp_path / "replay.png", sc.grid).stat().st_size > 10_000


def test_batches_and_bad_telemetry(unknown_plant):
    sc, tel, plant = unknown_plant
    spec = SPEC["open_loop"]
    batches = list(TelemetryBatches(tel, spec, plant.dm_response(), plant.dm_gain, batch_frames=700))
    assert sum(x.shape[0] for x, _ in batches) == tel.y.shape[0] - spec.first_frame
    x, t = batches[0]
    assert x.shape[1:] == (sc.grid.n_actuators, spec.n_taps) and t.shape[1:] == (sc.grid.n_actuators,)
    short = Telemetry(y=tel.y[:5], wfs=tel.wfs[:5], delay_frames=2)
    with pytest.raises(TelemetryError, match="5 frames"):
        fit_from_telemetry(short, spec, plant=plant)
    with pytest.raises(TelemetryError, match="delay_frames=2 but the history asks for delay_frames=3"):
        fit_from_telemetry(tel, HistorySpec("open_loop", 4, 3), plant=plant)
    assert ActuatorGrid.from_positions(tel.positions_m) == sc.grid
    with pytest.raises(TelemetryError, match="row-major"):
        ActuatorGrid.from_positions(tel.positions_m.flip(0))
    with pytest.raises(TelemetryError, match="misregistered DM model needs the actuator grid"):
        fit_from_telemetry(Telemetry(y=tel.y, wfs=tel.wfs, delay_frames=2), spec, plant={"misregistration_x": 0.2})
    assert torch.isfinite(fit_from_telemetry(tel, spec, plant={"dm_gain": 2.0}).network.weight).all()


@pytest.mark.slow
def test_mlp_by_sgd_and_checkpoints(unknown_plant, tmp_path):
    """Any network trains on telemetry through the one Lightning task; the checkpoint says it learnt from telemetry."""
    sc, tel, plant = unknown_plant
    spec = SPEC["open_loop"]
    mlp = {"class_path": "MLP", "init_args": {"hidden": [16], "scale_nm": 50.0}}
    fitted = fit_from_telemetry(tel, spec, mlp, plant=plant, data=TelemetryDataConfig(val_frames=500),
                                output=FitOutput(tmp_path / "mlp.ckpt"),
                                optimization=OptimizationConfig(fit_method="sgd", lr=3e-3, epochs=2, accelerator="cpu"))
    assert fitted.val_loss is not None and fitted.train_loss is not None
    loaded = load_predictor(tmp_path / "mlp.ckpt", sc)
    assert loaded.info["targets"] == "telemetry" and loaded.info["dm_gain_model"] == pytest.approx(2.0, rel=0.02)
    history = torch.randn(7, sc.grid.n_actuators, spec.n_taps, generator=torch.Generator().manual_seed(0),
                          dtype=torch.float64)
    assert torch.allclose(loaded.network(history), fitted.network(history))
    linear = fit_from_telemetry(tel, spec, plant=plant, data=TelemetryDataConfig(val_frames=500),
                                output=FitOutput(tmp_path / "eof.ckpt"))
    assert linear.val_loss < fitted.val_loss  # a linear EOF in closed form beats a 2-epoch MLP here
    assert torch.equal(load_predictor(tmp_path / "eof.ckpt").network.weight, linear.network.weight)


@pytest.mark.slow
def test_fit_from_the_telemetry_a_scenario_produces():
    """compare's predictor that does not learn from simulator truth: record, identify, fit, all inside eofnn."""
    sc = scenario(dm_gain=2.0, wfs_noise_nm=2.0)
    data = DataConfig(frames=3000, val_frames=500, integrator_gain=0.3, seed=4)
    fitted = fit_from_scenario_telemetry(sc, "open_loop", 4, data=data)
    assert fitted.info["targets"] == "telemetry" and abs(fitted.info["identified_plant"]["dm_gain"] - 2.0) < 0.04
    assert closed_loop_rms(sc, fitted.controller()) < 0.5 * closed_loop_rms(sc, Integrator(0.3))
    with pytest.raises(ConfigError, match="dither_nm=0.0 is invalid"):
        fit_from_scenario_telemetry(sc, "open_loop", 4, data=DataConfig(dither_nm=0.0))
