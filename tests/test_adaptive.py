"""Online adaptation: RLS and recompute-and-blend filters learning from telemetry while the loop runs."""

from __future__ import annotations

import pytest
import torch

from eofnn.control.adaptive import BlendController, RLSController, integrator_filter
from eofnn.data.history import HistorySpec
from eofnn.data.stream import DataConfig
from eofnn.errors import ConfigError
from eofnn.sim import run_loop
from eofnn.training.fit import fit_predictor

FAST = DataConfig(frames=3000, val_frames=500, sequence_frames=1000, dither_nm=10.0)


@pytest.fixture
def noisy(small_scenario):
    return small_scenario.with_plant(wfs_noise_nm=5.0)


def tail_rms(scenario, controller, n_frames=4000, plant=None):
    result = run_loop(scenario.turbulence(9), plant or scenario.plant, controller, n_frames, record=())
    return result, result.residual_rms_nm[0, n_frames // 2:].median().item()


@pytest.mark.slow
@pytest.mark.parametrize("kind, history_length", [("open_loop", 4), ("closed_loop", 5)])
def test_rls_and_blend_converge_to_the_fitted_filter(noisy, kind, history_length):
    spec = HistorySpec(kind, history_length, 2)
    fitted = fit_predictor(noisy, kind, history_length, data=FAST).predictor
    _, static = tail_rms(noisy, fitted.controller())
    # Closed-loop blend needs excitation: unexcited closed-loop normal equations are (near-)singular.
    blend_dither = 2.0 if kind == "closed_loop" else 0.0
    for controller in (RLSController(spec, forgetting=0.999),
                       BlendController(spec, every_frames=250, window_frames=1000, gain=0.5, dither_nm=blend_dither)):
        result, adaptive = tail_rms(noisy, controller)
        assert not result.diverged and controller.fallback_frame is None
        assert adaptive < 1.2 * static, (type(controller).__name__, adaptive, static)
    # They started from the integrator-equivalent filter, which is far worse.
    _, start = tail_rms(noisy, BlendController(spec, integrator_filter(spec, 0.5 if kind == "closed_loop" else 1.0),
                                               every_frames=10**6, window_frames=10**6))
    assert static < 0.5 * start


@pytest.mark.slow
@pytest.mark.parametrize("make", [
    lambda spec, w: RLSController(spec, w, forgetting=0.999, integrator_gain=0.2),
    lambda spec, w: BlendController(spec, w, every_frames=200, integrator_gain=0.2),
])
def test_fallback_engages_when_the_loop_is_unstable(noisy, make):
    """Open-loop EOF with a DM applying 3x the command (margin ~1.4x): the fallback integrator takes over."""
    spec = HistorySpec("open_loop", 4, 2)
    fitted = fit_predictor(noisy, "open_loop", 4, data=FAST).predictor
    controller = make(spec, fitted.network.weight)
    plant = noisy.with_plant(dm_gain=3.0).plant
    result = run_loop(noisy.turbulence(9), plant, controller, 1500, record=())
    assert not result.diverged
    assert controller.fallback_frame is not None and controller.fallback_frame < 50
    assert int(controller.fallback_frames[0]) == controller.fallback_frame
    assert result.residual_rms_nm[0, -500:].median() < 0.2 * result.turbulence_rms_nm[0, -500:].median()
    # The same controller in the nominal loop does not fall back.
    nominal = make(spec, fitted.network.weight)
    assert not run_loop(noisy.turbulence(9), noisy.plant, nominal, 1500, record=()).diverged
    assert nominal.fallback_frame is None


class SteppedTurbulence:
    """A turbulence stream with a static shape added from ``step_frame`` on (a sudden, then frozen, change)."""

    def __init__(self, turbulence, step_frame: int, shape_nm: torch.Tensor) -> None:
        self.turbulence, self.step_frame, self.shape_nm = turbulence, step_frame, shape_nm
        self.grid, self.n_realisations = turbulence.grid, turbulence.n_realisations

    def chunks(self, n_frames: int, chunk: int = 1024, start: int = 0):
        for first, frames in self.turbulence.chunks(n_frames, chunk, start):
            after = torch.arange(first, first + frames.shape[1]) >= self.step_frame
            yield first, frames + after.view(1, -1, 1) * self.shape_nm


@pytest.mark.slow
def test_a_transient_does_not_trigger_the_fallback_unless_patience_is_one(noisy):
    spec = HistorySpec("open_loop", 4, 2)
    fitted = fit_predictor(noisy, "open_loop", 4, data=FAST).predictor
    shape = 150.0 * torch.randn(noisy.grid.n_actuators, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    outcomes = {}
    for patience in (None, 1):
        controller = RLSController(spec, fitted.network.weight, forgetting=0.999, fallback_patience=patience)
        result = run_loop(SteppedTurbulence(noisy.turbulence(9), 600, shape), noisy.plant, controller, 1000, record=())
        assert not result.diverged
        outcomes[patience] = controller.fallback_frame
    assert outcomes[None] is None  # the step leaves the history after p + d frames: no fallback
    assert outcomes[1] is not None and 600 <= outcomes[1] < 610  # an impatient guard takes the spike for divergence


def random_regression(n_frames, n_actuators, taps, seed=0):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n_frames, 1, n_actuators, taps, generator=gen, dtype=torch.float64)
    true = torch.randn(n_actuators, taps, generator=gen, dtype=torch.float64)
    t = (x * true).sum(-1) + 0.1 * torch.randn(n_frames, 1, n_actuators, generator=gen, dtype=torch.float64)
    return x, t


@pytest.mark.parametrize("forgetting", [1.0, 0.98])
def test_rls_is_exponentially_weighted_ridge(forgetting):
    """RLS from w0 with P0 = I / delta equals argmin sum lambda^(N-i) (t_i - w x_i)^2 + lambda^N delta |w - w0|^2."""
    spec = HistorySpec("open_loop", 3, 2)
    n_frames, n_act = 60, 4
    x, t = random_regression(n_frames, n_act, 3)
    w0 = torch.full((n_act, 3), 0.3, dtype=torch.float64)
    rls = RLSController(spec, w0, forgetting=forgetting, prior_frames=2.0)
    rls.reset(1, n_act, 2, torch.float64)
    for i in range(n_frames):
        rls.update(x[i], t[i])
    delta = 2.0 * x[0, 0].pow(2).mean(-1)  # prior_frames x mean square of the first regressor
    weight = forgetting ** torch.arange(n_frames - 1, -1, -1, dtype=torch.float64)
    xs, ts = x[:, 0].transpose(0, 1), t[:, 0].transpose(0, 1)  # (K, N, taps), (K, N)
    prior = (forgetting ** n_frames) * delta
    gram = torch.einsum("n,knf,kng->kfg", weight, xs, xs) + prior.view(-1, 1, 1) * torch.eye(3, dtype=torch.float64)
    cross = torch.einsum("n,knf,kn->kf", weight, xs, ts) + prior.view(-1, 1) * w0
    expected = torch.linalg.solve(gram, cross)
    torch.testing.assert_close(rls.weights[0], expected, rtol=1e-8, atol=1e-10)


def test_blend_refit_is_the_sliding_window_ridge_blended():
    spec = HistorySpec("closed_loop", 2, 2)
    n_act, every, window = 3, 10, 30
    x, t = random_regression(55, n_act, 4, seed=1)
    blend = BlendController(spec, torch.zeros(1, 4, dtype=torch.float64), every_frames=every, window_frames=window,
                            gain=0.25, alpha=1e-3)
    blend.reset(1, n_act, 2, torch.float64)
    before = None
    for i in range(50):
        if i == 49:
            before = blend.weights.clone()
        blend._learn(x[i], t[i], i)
    assert blend.refits == 5
    xs, ts = x[20:50, 0].transpose(0, 1), t[20:50, 0].transpose(0, 1)  # the last three blocks
    gram = xs.transpose(1, 2) @ xs
    alpha = 1e-3 * gram.diagonal(dim1=1, dim2=2).mean(-1)
    solution = torch.linalg.solve(gram + alpha.view(-1, 1, 1) * torch.eye(4, dtype=torch.float64),
                                  (xs.transpose(1, 2) @ ts.unsqueeze(-1)).squeeze(-1))
    torch.testing.assert_close(blend.weights[0], 0.75 * before[0] + 0.25 * solution, rtol=1e-9, atol=1e-12)


@pytest.mark.slow
def test_dithered_adaptation_is_reproducible(noisy):
    spec = HistorySpec("closed_loop", 3, 2)

    def run(seed):
        controller = RLSController(spec, forgetting=0.99, dither_nm=3.0, seed=seed)
        return run_loop(noisy.turbulence(1), noisy.plant, controller, 300, record=("y",)).telemetry.y

    first, again, other = run(4), run(4), run(5)
    assert torch.equal(first, again) and not torch.equal(first, other)


@pytest.mark.parametrize("make, match", [
    (lambda s: RLSController(s, forgetting=1.5), "forgetting=1.5"),
    (lambda s: RLSController(s, forgetting=0.0), "forgetting=0.0"),
    (lambda s: BlendController(s, gain=0.0), "gain=0.0"),
    (lambda s: BlendController(s, gain=1.2), "gain=1.2"),
    (lambda s: BlendController(s, every_frames=0), "every_frames=0"),
    (lambda s: BlendController(s, every_frames=100, window_frames=50), "window_frames=50"),
    (lambda s: RLSController(s, torch.zeros(3, 5)), r"initial_weights of shape \(3, 5\)"),
    (lambda s: RLSController(s, dither_nm=-1.0), "dither_nm=-1.0"),
    (lambda s: RLSController(s, torch.zeros(3, 4)).reset(1, 76, 2, torch.float64), "n_actuators=76"),
    (lambda s: RLSController(s).reset(1, 76, 3, torch.float64), "delay_frames=3"),
])
def test_bad_values_are_one_line_errors(make, match):
    with pytest.raises(ConfigError, match=match) as info:
        make(HistorySpec("open_loop", 4, 2))
    assert "\n" not in str(info.value)
