"""Predictors and the one training loop: closed form vs direct solves, SGD, the study's orderings, checkpoints."""

from __future__ import annotations

import subprocess
import sys
import warnings
from dataclasses import fields

import pytest
import torch
from torch import nn

from eofnn.control import Dithered, Integrator, PredictiveController, PseudoIntegrator
from eofnn.data.history import HistorySpec, build_history, targets
from eofnn.data.stream import DataConfig, LoopDataModule, SimulatedTelemetry
from eofnn.errors import CheckpointError, CollinearityWarning, ConfigError, OutputExistsError
from eofnn.models.linear import LinearFilter
from eofnn.sim import run_loop
from eofnn.training.checkpoint import load_predictor
from eofnn.training.fit import FitOutput, fit_predictor
from eofnn.training.ridge import NormalEquations, fit_closed_form
from eofnn.training.task import OptimizationConfig

FAST = dict(frames=3000, val_frames=500, sequence_frames=1000)
DATA_FIELDS = {f.name for f in fields(DataConfig)}


def fit(scenario, kind, history_length, network=None, checkpoint_path=None, **options):
    """fit_predictor with the options of both groups given flat (data fields, the rest optimisation)."""
    data = DataConfig(**{k: v for k, v in options.items() if k in DATA_FIELDS})
    optimization = OptimizationConfig(**{k: v for k, v in options.items() if k not in DATA_FIELDS})
    return fit_predictor(scenario, kind, history_length, network, data=data, optimization=optimization,
                         output=FitOutput(checkpoint_path))


def recorder(gain=0.4, dither_nm=5.0):
    return Dithered(Integrator(gain), dither_nm)


def median_rms(scenario, controller, n_frames=1500, seed=9):
    result = run_loop(scenario.turbulence(seed), scenario.plant, controller, n_frames, record=())
    if result.diverged:
        return float("inf")
    return result.residual_rms_nm[:, 100:].median().item()


def all_batches(dataset):
    xs, ts = zip(*dataset, strict=False)
    return torch.cat(xs), torch.cat(ts)


def test_history_tensors_follow_the_conventions():
    t, k = 30, 3
    s = torch.arange(t * k, dtype=torch.float64).reshape(t, k)
    y, wfs = -2 * s, 5 * s
    spec = HistorySpec("open_loop", 3, 2)
    x = build_history(spec, s=s)
    n = spec.first_frame  # = d + p - 1 = 4
    assert n == 4 and x.shape == (t - n, k, 3)
    torch.testing.assert_close(x[0], torch.stack([s[2], s[1], s[0]], -1))
    torch.testing.assert_close(build_history(spec, y=y, wfs=wfs)[0, :, 0], wfs[2] - y[2])  # POL value
    cl = HistorySpec("closed_loop", 3, 2)
    xc = build_history(cl, y=y, wfs=wfs)
    torch.testing.assert_close(xc[0], torch.stack([y[3], y[2], y[1], wfs[2], wfs[1], wfs[0]], -1))
    torch.testing.assert_close(targets(s, cl, dm_gain=2.0)[0], -s[4] / 2)


@pytest.mark.parametrize("kind", ["open_loop", "closed_loop"])
def test_predictive_controller_sees_the_same_histories_as_training(small_scenario, kind):
    spec = HistorySpec(kind, 3, 2)

    class Recorder(nn.Module):
        def __init__(self):
            super().__init__()
            self.w = nn.Parameter(torch.zeros(1, dtype=torch.float64))
            self.seen = []

        def forward(self, history):
            self.seen.append(history.clone())
            return -0.3 * history[..., -1]  # any command, so that y and eps differ

    net = Recorder()
    controller = recorder(0.3) if kind == "closed_loop" else None
    result = run_loop(small_scenario.turbulence(0), small_scenario.plant,
                      PredictiveController(net, spec), 60)
    tel = result.telemetry
    expected = build_history(spec, y=tel.y, wfs=tel.wfs)[0]
    seen = torch.stack(net.seen)[:, 0]  # calls start at first_frame
    torch.testing.assert_close(seen, expected[: len(seen)])
    assert controller is None or kind == "closed_loop"


class _Forward(nn.Module):
    """A LinearFilter behind a module that is not one: the controller's general path."""

    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, history):
        return self.net(history)


@pytest.mark.slow
@pytest.mark.parametrize("kind, structure, history_length, dm_gain", [
    ("closed_loop", "per_actuator", 3, 1.0), ("closed_loop", "shared", 1, 1.0),
    ("open_loop", "per_actuator", 4, 1.0), ("open_loop", "shared", 1, 1.5), ("open_loop", "per_actuator", 3, 1.5)])
def test_linear_filter_fast_path_gives_the_commands_of_forward_bit_for_bit(small_scenario, kind, structure,
                                                                           history_length, dm_gain):
    """PredictiveController's LinearFilterStep and LinearFilter.forward on the general path: the same commands to
    the last bit over 300 frames (a ring wrap), with noise, two realisations and a POL gain other than 1."""
    sc = small_scenario.with_plant(dm_gain=dm_gain, wfs_noise_nm=2.0)
    spec = HistorySpec(kind, history_length, sc.delay_frames)
    net = LinearFilter(sc.grid.n_actuators, spec.n_taps, structure)
    with torch.no_grad():
        net.weight.normal_(0.0, 0.01, generator=torch.Generator().manual_seed(3))
        net.weight[:, 0] += 1.0 if kind == "closed_loop" else -1.0 / dm_gain  # integrator / POL predictor
        if kind == "closed_loop":
            net.weight[:, history_length] -= 0.4
    turbulence, runs = sc.turbulence(0, n_realisations=2), {}
    for name, network in (("fast", net), ("general", _Forward(net))):
        controller = PredictiveController(network, spec, dm_gain_model=dm_gain)
        runs[name] = run_loop(turbulence, sc.plant, controller, 300, record=("s", "y"))
        assert (controller._fast is not None) == (name == "fast")
    assert torch.equal(runs["fast"].telemetry.s, runs["general"].telemetry.s)
    assert not runs["fast"].diverged
    assert runs["fast"].telemetry.y.abs().max() > 0
    assert torch.equal(runs["fast"].telemetry.y, runs["general"].telemetry.y)


@pytest.mark.slow
@pytest.mark.parametrize("structure", ["per_actuator", "shared", "neighbourhood"])
def test_streamed_closed_form_equals_direct_ridge(small_scenario, structure):
    noisy = small_scenario.with_plant(wfs_noise_nm=5.0)
    spec = HistorySpec("open_loop", 3, 2)
    grid = {"diameter_m": 2.0, "n_across": 10, "obstruction": 0.0}
    net = LinearFilter(noisy.grid.n_actuators, spec.n_taps, structure, radius=1.0, grid=grid)
    dataset = SimulatedTelemetry(noisy, spec, 1200, data=DataConfig(seed=1, sequence_frames=600, batch_frames=97))
    fit_closed_form(net, dataset, alpha=1e-3, alpha_relative=True)
    x, t = all_batches(dataset)
    features, target = net.features(x), net.group_targets(t)
    gram = features.transpose(1, 2) @ features
    alpha = 1e-3 * gram.diagonal(dim1=1, dim2=2).mean(-1)
    direct = torch.linalg.solve(gram + alpha.view(-1, 1, 1) * torch.eye(gram.shape[-1], dtype=gram.dtype),
                                (features.transpose(1, 2) @ target.unsqueeze(-1))).squeeze(-1)
    torch.testing.assert_close(net.weight.detach(), direct, rtol=1e-6, atol=0)
    if structure == "neighbourhood":
        return  # 27 correlated regressors: without regularisation the problem is too ill-conditioned to compare
    # Without regularisation it is the least-squares solution.
    ne = NormalEquations()
    ne.update(features, target)
    lstsq = torch.linalg.lstsq(features, target.unsqueeze(-1)).solution.squeeze(-1)
    torch.testing.assert_close(ne.solve(0.0).weights, lstsq, rtol=1e-6, atol=1e-9)


@pytest.mark.slow
def test_sgd_reaches_the_closed_form_loss(small_scenario):
    noisy = small_scenario.with_plant(wfs_noise_nm=20.0)
    spec = HistorySpec("open_loop", 3, 2)
    # One full-data batch per epoch: L-BFGS is a deterministic quasi-Newton method on it.
    common = dict(frames=1500, val_frames=300, sequence_frames=1500, batch_frames=1500, seed=3)
    closed = fit(noisy, "open_loop", 3, **common)
    sgd = fit(noisy, "open_loop", 3, fit_method="sgd", optimizer="lbfgs", lr=1.0, epochs=3, **common)
    x, t = all_batches(SimulatedTelemetry(noisy, spec, 1500, data=DataConfig(seed=3, sequence_frames=1500)))
    with torch.no_grad():
        loss_closed = (closed.predictor.network(x) - t).pow(2).mean().item()
        loss_sgd = (sgd.predictor.network(x) - t).pow(2).mean().item()
    assert loss_closed <= loss_sgd * (1 + 1e-9)
    assert loss_sgd < 1.01 * loss_closed


@pytest.mark.slow
def test_study_orderings_in_a_frozen_flow_loop(small_scenario):
    """OL EOF beats the pseudo-integrator 5x; CL EOF ~ OL EOF nominally; under a 2x DM gain CL holds, OL fails."""
    pseudo = median_rms(small_scenario, PseudoIntegrator())
    ol = fit(small_scenario, "open_loop", 4, **FAST).predictor
    cl = fit(small_scenario, "closed_loop", 5, dither_nm=10.0, **FAST).predictor
    ol_nominal, cl_nominal = median_rms(small_scenario, ol.controller()), median_rms(small_scenario, cl.controller())
    assert ol_nominal * 5 < pseudo
    assert cl_nominal < 1.5 * ol_nominal
    doubled = small_scenario.with_plant(dm_gain=2.0)
    cl2 = fit(doubled, "closed_loop", 5, dither_nm=10.0, integrator_gain=0.25,
                        **FAST).predictor
    assert median_rms(doubled, cl2.controller()) < 1.5 * cl_nominal
    result = run_loop(doubled.turbulence(9), doubled.plant, ol.controller(), 1500, record=())
    assert result.diverged or result.residual_rms_nm[:, 100:].median().item() > 10 * ol_nominal


@pytest.mark.slow
def test_unexcited_closed_loop_data_is_flagged(small_scenario):
    with pytest.warns(CollinearityWarning):
        result = fit(small_scenario, "closed_loop", 4, dither_nm=0.0, **FAST)
    # Honest either way: if it is used regardless, the loop result is reported, diverged or not.
    loop = run_loop(small_scenario.turbulence(9), small_scenario.plant, result.predictor.controller(), 500,
                    record=())
    assert loop.diverged or torch.isfinite(loop.residual_rms_nm).all()


@pytest.mark.slow
def test_refit_rounds_record_with_the_fitted_predictor(small_scenario):
    result = fit(small_scenario, "closed_loop", 5, dither_nm=10.0, refit_rounds=1, **FAST)
    assert [r["round"] for r in result.rounds] == [0, 1]
    assert median_rms(small_scenario, result.predictor.controller()) < median_rms(small_scenario, PseudoIntegrator()) / 5


@pytest.mark.slow
def test_mlp_trains_through_the_same_loop_and_runs_closed_loop(small_scenario):
    pseudo = median_rms(small_scenario, PseudoIntegrator())
    result = fit(small_scenario, "open_loop", 4,
                           {"class_path": "MLP", "init_args": {"hidden": [16, 16]}}, fit_method="sgd", lr=3e-3,
                           epochs=3, batch_frames=64, **FAST)
    assert result.val_loss < result.rounds[0]["train_loss"] * 2
    assert median_rms(small_scenario, result.predictor.controller()) < pseudo / 3
    with pytest.raises(ConfigError, match="closed_form"):
        fit(small_scenario, "open_loop", 4, {"class_path": "MLP"}, **FAST)


@pytest.mark.slow
def test_sgd_fits_are_reproducible_bit_for_bit(small_scenario):
    def weights(seed):
        return fit(small_scenario, "open_loop", 3, {"class_path": "MLP", "init_args": {"hidden": [8]}},
                   fit_method="sgd", epochs=1, seed=seed, frames=600, val_frames=200,
                   sequence_frames=300).predictor.network.state_dict()

    first, again, other = weights(5), weights(5), weights(6)
    assert all(torch.equal(first[k], again[k]) for k in first)
    assert not all(torch.equal(first[k], other[k]) for k in first)


@pytest.mark.cli
@pytest.mark.slow
def test_checkpoint_round_trip_in_another_process(small_scenario, tmp_path):
    path = tmp_path / "ol.ckpt"
    result = fit(small_scenario, "open_loop", 4, checkpoint_path=path, **FAST)
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    assert ckpt["hyper_parameters"]["spec"]["history_length"] == 4
    x = torch.randn(5, small_scenario.grid.n_actuators, 4, dtype=torch.float64) * 100
    torch.save(x, tmp_path / "x.pt")
    code = (
        "import torch, sys; from eofnn.training.checkpoint import load_predictor;"
        f"p = load_predictor({str(path)!r}); x = torch.load({str(tmp_path / 'x.pt')!r}, weights_only=True);"
        f"torch.save(p.network(x).detach(), {str(tmp_path / 'y.pt')!r})"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    other = torch.load(tmp_path / "y.pt", weights_only=True)
    assert torch.equal(other, result.predictor.network(x).detach())
    with pytest.raises(OutputExistsError):
        fit(small_scenario, "open_loop", 4, checkpoint_path=path, **FAST)


@pytest.mark.slow
def test_checkpoint_into_an_incompatible_setup_fails_clearly(small_scenario, tmp_path):
    path = tmp_path / "ol.ckpt"
    fit(small_scenario, "open_loop", 4, checkpoint_path=path, **FAST)
    bigger = small_scenario.__class__(grid={"diameter_m": 2.0, "n_across": 12}, atmosphere=small_scenario.atmosphere)
    with pytest.raises(CheckpointError, match="n_actuators=80 but the scenario has n_actuators=112"):
        load_predictor(path, bigger)
    slower = small_scenario.with_plant(delay_frames=3)
    with pytest.raises(CheckpointError, match="delay_frames=2 but the scenario has delay_frames=3"):
        load_predictor(path, slower)
    with pytest.raises(CheckpointError, match="history_length=4 but history_length=6"):
        load_predictor(path, small_scenario, history_length=6)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_predictor(tmp_path / "missing.ckpt")
    (tmp_path / "junk.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not an eofnn predictor checkpoint"):
        load_predictor(tmp_path / "junk.ckpt")


@pytest.mark.slow
def test_workers_never_share_frames_and_seeds_reproduce(small_scenario):
    spec = HistorySpec("open_loop", 3, 2)
    dm = LoopDataModule(small_scenario, spec, DataConfig(frames=1200, val_frames=300, sequence_frames=300, seed=4,
                                                   num_workers=2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        two_workers = all_batches(dm.train_dataloader())[1]
    one_worker = all_batches(SimulatedTelemetry(small_scenario, spec, 1200, data=DataConfig(seed=4, sequence_frames=300)))[1]
    # Same sequences whatever the number of workers (order may interleave), none repeated.
    assert sorted(two_workers[:, 0].tolist()) == sorted(one_worker[:, 0].tolist())
    firsts = [seq[1][0, 0, 0].item() for seq in map(SimulatedTelemetry(
        small_scenario, spec, 1200, data=DataConfig(seed=4, sequence_frames=300)).sequence, range(4))]
    assert len(set(firsts)) == 4
    val = all_batches(dm.val_dataloader())[1]
    assert not torch.isin(val[:, 0], one_worker[:, 0]).any()


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["open_loop", "closed_loop"])
def test_batches_are_windows_of_the_whole_sequence(small_scenario, kind):
    dataset = SimulatedTelemetry(small_scenario, HistorySpec(kind, 3, 2), 500,
                                 data=DataConfig(seed=2, sequence_frames=500, batch_frames=37),
                                 data_controller=recorder())
    history, target = dataset.sequence(0)
    x, t = all_batches(dataset)
    assert torch.equal(x, history[0]) and torch.equal(t, target[0])


@pytest.mark.slow
def test_an_mlp_with_a_neighbourhood_trains_and_reloads(small_scenario, tmp_path):
    """The neighbourhood MLP (radius > 0) of the fair contest's structure x nonlinearity table."""
    network = {"class_path": "eofnn.models.mlp.MLP", "init_args": {"hidden": [8], "radius": 1.5}}
    result = fit(small_scenario, "open_loop", 3, network, checkpoint_path=tmp_path / "mlp.ckpt", fit_method="sgd",
                 epochs=1, frames=600, val_frames=200, sequence_frames=600, batch_frames=100)
    net = result.predictor.network
    assert net.neighbours.shape == (small_scenario.grid.n_actuators, 9)
    loaded = load_predictor(tmp_path / "mlp.ckpt")
    x = torch.randn(5, small_scenario.grid.n_actuators, 3, dtype=torch.float64)
    with torch.no_grad():
        assert torch.equal(loaded.network(x.float()), net(x.float()))
