"""The classical baselines (POL extrapolator, optimal modal integrator, AR(2) LQG) against their analytic behaviour."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
import yaml

from eofnn.analysis.linear import controller_stability, modal_stability
from eofnn.analysis.stability import LoopSetup, analyse_polynomials
from eofnn.cli.main import main
from eofnn.control.baselines import critical_gain
from eofnn.control.classical import Extrapolator, ModalIntegrator, extrapolation_weights, extrapolator_filter
from eofnn.control.kalman import fit_ar2, kalman_gain, prediction_error_variance
from eofnn.control.modal import build_lqg, critical_integrator_gain, integrator_transfer, modal_statistics
from eofnn.data.history import HistorySpec, blended_target, open_loop_history
from eofnn.data.stream import DataConfig
from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
from eofnn.evaluation.experiment import Experiment
from eofnn.sim.loop.runner import run_loop

TINY_SCENARIO = Path(__file__).parent / "conf" / "tiny_scenario.yaml"
F64 = torch.float64


# -- extrapolator ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("delay", [1, 2, 3, 1.5, 2.25])
@pytest.mark.parametrize("order", [1, 2])
def test_extrapolator_is_exact_on_polynomials_of_its_order(order, delay):
    n = torch.arange(40, dtype=F64)
    s = torch.stack([3.0 - 2.0 * n, 1.0 + 0.5 * n - 0.25 * n**2], -1)  # (frames, 2 actuators)
    network, spec = extrapolator_filter(order, delay)
    prediction = -network(open_loop_history(s, spec))  # commands are -prediction (g_model = 1)
    target = blended_target(s, spec)
    exact = slice(None) if order == 2 else slice(0, 1)  # order 1 is exact on the linear column only
    torch.testing.assert_close(prediction[:, exact], target[:, exact], rtol=0, atol=1e-9)
    if order == 1:
        assert (prediction[:, 1] - target[:, 1]).abs().min() > 0.1  # ... and not on the quadratic one


def test_extrapolator_weights_of_the_issue():
    torch.testing.assert_close(extrapolation_weights(1, 2), torch.tensor([3.0, -2.0], dtype=F64))
    torch.testing.assert_close(extrapolation_weights(0, 2), torch.tensor([1.0], dtype=F64))
    torch.testing.assert_close(extrapolation_weights(2, 2), torch.tensor([6.0, -8.0, 3.0], dtype=F64))
    # Fractional delay 1.5: half of the 1-frame and half of the 2-frame extrapolation.
    torch.testing.assert_close(extrapolation_weights(1, 1.5), torch.tensor([2.5, -1.5], dtype=F64))


@pytest.mark.physics
@pytest.mark.parametrize("order, delay", [(1, 2), (2, 2), (1, 1.5)])
def test_extrapolator_error_on_a_sinusoid_is_the_analytic_one(order, delay):
    omega = 0.2  # rad/frame
    n = torch.arange(4000, dtype=F64)
    s = torch.cos(omega * n).unsqueeze(-1)
    network, spec = extrapolator_filter(order, delay)
    error = (blended_target(s, spec) + network(open_loop_history(s, spec))).detach()
    d, f = divmod(delay, 1)
    # Target (1 - f) e^{iwn} + f e^{iw(n+1)}; prediction sum_j w_j e^{iw(n - d - j)}.
    weights = extrapolation_weights(order, delay)
    taps = torch.exp(-1j * omega * (d + torch.arange(len(weights), dtype=F64)))
    amplitude = abs((1 - f) + f * complex(math.cos(omega), math.sin(omega)) - complex((weights * taps).sum()))
    assert float(error.pow(2).mean().sqrt()) == pytest.approx(amplitude / math.sqrt(2), rel=2e-3)


@pytest.mark.physics
def test_extrapolator_in_the_loop_leaves_exactly_its_prediction_error(small_scenario):
    """Noise-free nominal loop: the POL values are the turbulence, so eps(n) = s(n) - 3 s(n-2) + 2 s(n-3)."""
    result = run_loop(small_scenario.turbulence(3, "test"), small_scenario.plant, Extrapolator(1), 300,
                      record=("s", "eps"))
    s, eps = result.telemetry.s[0], result.telemetry.eps[0]
    expected = s[3:] - 3 * s[1:-2] + 2 * s[:-3]
    torch.testing.assert_close(eps[3:], expected, rtol=0, atol=1e-9)


@pytest.mark.physics
def test_extrapolator_stability_is_that_of_its_open_loop_filter(small_scenario):
    result = controller_stability(PredictorConfig(controller="extrapolator", order=1), None, small_scenario)
    assert result.stable and result.kind == "open_loop"
    low, high = result.gain_margin
    assert 0.5 < low < 1 < high < 1.5
    # The same filter simulated just outside its analytic interval diverges, just inside it does not.
    for gain, diverges in ((high * 0.97, False), (high * 1.1, True)):
        plant = small_scenario.with_plant(dm_gain=gain)
        run = run_loop(plant.turbulence(1, "test"), plant.plant, Extrapolator(1), 3000, record=(),
                       divergence_factor=5.0)
        assert run.diverged == diverges, gain


# -- modal integrator ---------------------------------------------------------------------------------------------
@pytest.mark.physics
@pytest.mark.parametrize("delay", [1, 2, 3])
def test_critical_gain_matches_the_closed_form(delay):
    assert critical_integrator_gain(delay) == pytest.approx(critical_gain(delay), abs=1e-9)
    assert critical_integrator_gain(delay, dm_gain=2.0) == pytest.approx(critical_gain(delay) / 2, abs=1e-9)


@pytest.mark.physics
@pytest.mark.parametrize("delay", [2, 1.5])
def test_integrator_transfer_matches_the_stability_analysis(delay):
    gains = torch.tensor([0.2, 0.5], dtype=F64)
    freqs = torch.tensor([1.0, 50.0, 200.0, 480.0], dtype=F64)
    omega = 2 * math.pi * freqs / 1000.0
    rejection, noise = integrator_transfer(gains, delay, 1.0, omega)
    setup = LoopSetup(delay_frames=delay)
    d_poly = torch.tensor([[1.0, -1.0]], dtype=F64).expand(2, 2)
    analysis = analyse_polynomials(d_poly, -gains.unsqueeze(1), setup, freqs)
    torch.testing.assert_close(rejection, analysis.rejection.abs() ** 2)
    torch.testing.assert_close(noise, analysis.noise_transfer.abs() ** 2)


@pytest.mark.physics
@pytest.mark.slow
def test_optimal_modal_gains_follow_signal_to_noise():
    """A random walk with little noise wants a high gain; pure white noise the lowest one searched."""
    gen = torch.Generator().manual_seed(0)
    walk = torch.randn(1, 8192, generator=gen, dtype=F64).cumsum(1) * 5
    pol = torch.stack([walk[0], torch.zeros(8192, dtype=F64)], -1).unsqueeze(0)
    pol = pol + torch.randn(pol.shape, generator=gen, dtype=F64)
    stats = modal_statistics(pol)
    assert float(stats.noise_variance.sqrt().min()) == pytest.approx(1.0, rel=0.1)
    from eofnn.control.modal import optimal_gains
    gains, residual, k_crit = optimal_gains(stats, 2)
    by_variance = stats.variance.argsort(descending=True)
    assert gains[by_variance[1]] < 0.05 < 0.3 < gains[by_variance[0]] < k_crit
    assert float(residual[by_variance[1]]) < 0.1  # the noise mode is left (almost) alone: no turbulence, no noise
    # The walk's chosen gain against a brute-force scan of the simulated scalar loop (delay 2, the same noise).
    x, v = walk[0], torch.randn(8192, generator=gen, dtype=F64)

    def simulated(k: float) -> float:
        y, eps = torch.zeros(8192, dtype=F64), torch.zeros(8192, dtype=F64)
        for n in range(8192):
            y[n] = (y[n - 1] - k * (eps[n - 2] + v[n - 2])) if n >= 2 else 0.0
            eps[n] = x[n] + y[n]
        return float(eps[500:].pow(2).mean())

    chosen = float(gains[by_variance[0]])
    scan = {k: simulated(k) for k in (0.2, 0.3, 0.4, 0.5, 0.6, 0.7)}
    assert simulated(chosen) <= 1.03 * min(scan.values())
    assert float(residual[by_variance[0]]) == pytest.approx(simulated(chosen), rel=0.15)


# -- AR(2), Kalman filter, LQG -------------------------------------------------------------------------------------
def _ar2_autocovariance(a1: float, a2: float, q: float) -> list[float]:
    c0 = q * (1 - a2) / ((1 + a2) * ((1 - a2) ** 2 - a1**2))
    rho1 = a1 / (1 - a2)
    return [c0, c0 * rho1, c0 * (a1 * rho1 + a2)]


@pytest.mark.physics
def test_yule_walker_recovers_an_ar2_with_the_noise_subtracted():
    a1, a2, q, noise = 1.8, -0.9, 2.0, 3.0
    autocov = torch.tensor([_ar2_autocovariance(a1, a2, q)], dtype=F64)
    autocov[:, 0] += noise
    ar, q_hat = fit_ar2(autocov, torch.tensor([noise], dtype=F64))
    torch.testing.assert_close(ar, torch.tensor([[a1, a2]], dtype=F64))
    assert float(q_hat) == pytest.approx(q, rel=1e-9)


@pytest.mark.physics
@pytest.mark.slow
def test_kalman_gain_matches_scipy_and_the_simulated_prediction_errors():
    from scipy.linalg import solve_discrete_are

    a1, a2, q, r = 1.6, -0.8, 1.0, 4.0
    ar = torch.tensor([[a1, a2]], dtype=F64)
    gain, prior = kalman_gain(ar, torch.tensor([q], dtype=F64), torch.tensor([r], dtype=F64))
    a = torch.tensor([[a1, a2], [1.0, 0.0]], dtype=F64)
    reference = solve_discrete_are(a.T.numpy(), [[1.0], [0.0]], [[q, 0.0], [0.0, 0.0]], [[r]])
    torch.testing.assert_close(prior[0], torch.from_numpy(reference))
    # A synthetic AR(2) series measured with white noise, filtered: the empirical one- and two-step prediction
    # errors are the theoretical ones.
    gen = torch.Generator().manual_seed(1)
    frames = 60000
    e = math.sqrt(q) * torch.randn(frames, generator=gen, dtype=F64)
    x = torch.zeros(frames, dtype=F64)
    for n in range(2, frames):
        x[n] = a1 * x[n - 1] + a2 * x[n - 2] + e[n]
    z = x + math.sqrt(r) * torch.randn(frames, generator=gen, dtype=F64)
    filt = (torch.eye(2, dtype=F64) - torch.outer(gain[0], torch.tensor([1.0, 0.0], dtype=F64))) @ a
    state = torch.zeros(2, dtype=F64)
    errors = {1: [], 2: []}
    for n in range(frames - 2):
        state = filt @ state + gain[0] * z[n]
        if n > 1000:
            errors[1].append(float(x[n + 1] - (a @ state)[0]))
            errors[2].append(float(x[n + 2] - (a @ a @ state)[0]))
    for lead in (1, 2):
        theory = float(prediction_error_variance(ar, torch.tensor([q], dtype=F64), prior, gain, lead)[0])
        measured = torch.tensor(errors[lead], dtype=F64).pow(2).mean()
        assert float(measured) == pytest.approx(theory, rel=0.04), lead
    assert float(prediction_error_variance(ar, torch.tensor([q], dtype=F64), prior, gain, 1)[0]) == pytest.approx(
        float(prior[0, 0, 0]))


@pytest.fixture(scope="module")
def lqg_model():
    from eofnn.sim.scenario import Scenario

    scenario = Scenario.from_yaml(TINY_SCENARIO).with_plant(wfs_noise_nm=1.0)
    return scenario, build_lqg(scenario, DataConfig(frames=2048, dither_nm=5.0, integrator_gain=0.4))


@pytest.mark.physics
@pytest.mark.slow
def test_lqg_analytic_roots_agree_with_the_simulated_loop(lqg_model):
    scenario, model = lqg_model
    result = modal_stability(model, LoopSetup.from_plant(scenario.plant, scenario.frame_rate_hz))
    assert result.stable and result.structure == "modal" and len(result.max_root_modulus) == model.modes.shape[0]
    low, high = result.gain_margin
    assert low < 0.9 and 1.1 < high < 5
    for gain, diverges in ((high * 0.95, False), (high * 1.15, True)):
        plant = scenario.with_plant(dm_gain=gain)
        run = run_loop(plant.turbulence(1, "test"), plant.plant, model, 3000, noise_seed=1, record=(),
                       divergence_factor=5.0)
        assert run.diverged == diverges, gain
        analytic = modal_stability(model, LoopSetup.from_plant(plant.plant, plant.frame_rate_hz))
        assert analytic.stable != diverges


@pytest.mark.physics
@pytest.mark.slow
def test_lqg_beats_the_integrator_where_it_is_servo_lag_limited(lqg_model):
    from eofnn.control.baselines import Integrator

    scenario, model = lqg_model
    rms = {}
    for name, controller in (("integrator", Integrator(0.9)), ("extrapolator", Extrapolator(1)), ("lqg", model)):
        run = run_loop(scenario.turbulence(1, "test"), scenario.plant, controller, 1500, noise_seed=1, record=())
        rms[name] = float(run.residual_rms_nm[:, 300:].median())
    assert rms["lqg"] < 0.5 * rms["integrator"]
    assert rms["lqg"] < 1.1 * rms["extrapolator"]
    assert model.info["dm_gain_from_dither"] == pytest.approx(1.0, abs=0.05)


@pytest.mark.physics
def test_modal_integrator_polynomials_and_loop_agree(small_scenario):
    k = small_scenario.grid.n_actuators
    modes = torch.linalg.qr(torch.randn(k, k, generator=torch.Generator().manual_seed(0), dtype=F64))[0]
    gains = torch.linspace(0.2, 0.9, k, dtype=F64)
    model = ModalIntegrator(modes, gains, 2)
    result = modal_stability(model, LoopSetup())
    assert result.gain_margin[1] == pytest.approx(1.0 / 0.9, rel=1e-6)  # the critical gain is 1 at delay 2


# -- bad input -----------------------------------------------------------------------------------------------------
def _classical_config(tmp_path, predictor: dict) -> Path:
    path = tmp_path / "classical.yaml"
    path.write_text(yaml.safe_dump({"scenario": str(TINY_SCENARIO), "scenarios": {"nominal": {}},
                                    "predictors": {"baseline": predictor},
                                    "evaluation": {"frames": 600, "settle_frames": 100, "psd_segment_frames": 256}}))
    return path


@pytest.mark.cli
@pytest.mark.parametrize("predictor, expected", [
    ({"controller": "extrapolator", "order": 3}, "order=3 is invalid"),
    ({"controller": "extrapolator", "order": 1.5}, "Got value: 1.5"),  # jsonargparse types it: order::
    ({"controller": "lqg", "data": {"frames": 2048, "dither_nm": 0.0}}, "data.dither_nm=0.0 is invalid"),
    ({"controller": "modal_integrator", "data": {"frames": 500}}, "need at least 1024 frames"),
    ({"controller": "lqg", "modes": 500, "data": {"frames": 2048}}, "modes=500 is invalid"),
    ({"controller": "integrator", "modes": 5}, "modes=5 is for controller"),
])
def test_bad_classical_configs_are_one_line_and_write_nothing(cli_error, tmp_path, predictor, expected):
    out = tmp_path / "out"
    cli_error(["compare", "--config", _classical_config(tmp_path, predictor), "--out", out], expected, out)


@pytest.mark.slow
def test_compare_records_the_classical_models(tmp_path, small_scenario):
    predictors = {"lqg": PredictorConfig(controller="lqg", modes=20, data=DataConfig(frames=1024, dither_nm=5.0)),
                  "modal": PredictorConfig(controller="modal_integrator", data=DataConfig(frames=1024, dither_nm=5.0)),
                  "extrapolator": PredictorConfig(controller="extrapolator", order=2)}
    experiment = Experiment(small_scenario, {"nominal": {}}, predictors,
                            EvaluationConfig(frames=400, settle_frames=100, psd_segment_frames=256), log=lambda _: None)
    result = experiment.run().to_json()
    models = result["classical_models"]["nominal"]
    assert set(models) == {"lqg", "modal"}
    assert models["lqg"]["own_modes"] == 20 and models["modal"]["own_modes"] == models["modal"]["n_modes"]
    assert set(result["stability"]["nominal"]) == {"lqg", "modal", "extrapolator"}
    assert all(entry["stable"] for entry in result["stability"]["nominal"].values())
    json.dumps(result)  # metrics.json-ready
    # Each step's peak resident memory so far: positive, never decreasing, one per step as the timings.
    peaks = list(result["peak_memory_bytes"].values())
    assert list(result["peak_memory_bytes"]) == list(result["timings_s"])
    assert all(p > 0 for p in peaks) and peaks == sorted(peaks)
    with pytest.raises(ConfigError, match="modes=500 is invalid"):
        Experiment(small_scenario, {"nominal": {}}, {"lqg": PredictorConfig(controller="lqg", modes=500)},
                   EvaluationConfig(frames=400, settle_frames=100, psd_segment_frames=256))


def test_history_spec_of_the_extrapolator():
    network, spec = extrapolator_filter(2, 1.5, dm_gain_model=2.0)
    assert spec == HistorySpec("open_loop", 3, 1.5)
    torch.testing.assert_close(network.weight[0], -extrapolation_weights(2, 1.5) / 2.0)


@pytest.mark.parametrize("delay", [2, 1.5, 3])
def test_lqg_polynomials_are_the_controller_it_runs(delay):
    """The impulse response of ``N / D`` (what the analysis sees) is the command sequence the controller computes
    from a unit WFS reading, with its POL coupling to its own past commands, for integer and fractional delays."""
    from eofnn.control.classical import ModalLQG
    from eofnn.sim.loop.runner import LoopInput

    ar = torch.tensor([[1.7, -0.75], [0.3, 0.1]], dtype=F64)
    q, r = torch.tensor([1.0, 2.0], dtype=F64), torch.tensor([0.5, 1.0], dtype=F64)
    gain, _ = kalman_gain(ar, q, r)
    modes = torch.tensor([[0.6, 0.8], [-0.8, 0.6]], dtype=F64)
    model = ModalLQG(modes, ar, q, r, gain, delay, dm_gain_model=1.3)
    d_poly, n_poly = model.polynomials()
    model.reset(1, 2, delay, F64)
    frames = 30
    commands = []
    for n in range(frames):
        wfs = modes[:, 0].unsqueeze(0) if n == 0 else torch.zeros(1, 2, dtype=F64)  # a unit reading on mode 0
        commands.append(model.step(LoopInput(n, wfs, torch.zeros(1, 2, dtype=F64)))[0] @ modes[:, 0])
    expected = torch.zeros(frames, dtype=F64)  # D y = N u with u = delta: y(n) = N_n - sum_j D_j y(n - j)
    for n in range(frames):
        acc = n_poly[0, n] if n < n_poly.shape[1] else 0.0
        for j in range(1, min(n, d_poly.shape[1] - 1) + 1):
            acc = acc - d_poly[0, j] * expected[n - j]
        expected[n] = acc
    torch.testing.assert_close(torch.stack(commands), expected, rtol=1e-9, atol=1e-12)


@pytest.mark.slow
def test_classical_models_use_the_dm_gain_their_dither_measures(lqg_model):
    """Built from telemetry, the LQG believes the plant it identified: a DM applying 2x the command is learnt, not
    assumed away (a dm_gain_model given in the config is kept instead)."""
    scenario, nominal = lqg_model
    doubled = scenario.with_plant(dm_gain=2.0)
    model = build_lqg(doubled, DataConfig(frames=2048, dither_nm=5.0, integrator_gain=0.2))
    assert model.dm_gain_model == pytest.approx(2.0, rel=0.03)
    assert model.info["dm_gain_model_source"] == "measured from the dither"
    run = run_loop(doubled.turbulence(1, "test"), doubled.plant, model, 1500, noise_seed=1, record=())
    base = run_loop(scenario.turbulence(1, "test"), scenario.plant, nominal, 1500, noise_seed=1, record=())
    assert not run.diverged
    assert float(run.residual_rms_nm[:, 300:].median()) < 1.2 * float(base.residual_rms_nm[:, 300:].median())
    given = build_lqg(doubled, DataConfig(frames=2048, dither_nm=5.0, integrator_gain=0.2), dm_gain_model=1.0)
    assert given.dm_gain_model == 1.0 and given.info["warnings"]


@pytest.mark.cli
@pytest.mark.slow
def test_eofnn_stability_analyses_classical_controllers(tmp_path, capsys):
    out = tmp_path / "stab"
    assert main(["stability", "--scenario", str(TINY_SCENARIO), "--controller", "{controller: extrapolator, order: 1}",
                 "--out", str(out)]) == 0
    result = json.loads((out / "stability.json").read_text())
    low, high = result["dm_gain_interval"]
    assert result["stable"] and low == pytest.approx(0.8, abs=0.01) and high == pytest.approx(1.25, abs=0.01)
    assert (out / "stability.png").stat().st_size > 0
    capsys.readouterr()
    for args in ([], ["--controller", "{controller: integrator}", "--checkpoint", "x.ckpt"]):
        code = main(["stability", "--scenario", str(TINY_SCENARIO), "--out", str(tmp_path / "bad"), *args])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and "either --checkpoint" in err[0] and not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_the_modal_gain_cap_is_chosen_in_closed_loop(lqg_model):
    """How near its critical gain a mode may go is chosen on a stream of its own, like the integrator's gain."""
    from eofnn.control.modal import GAIN_MARGIN_CANDIDATES, build_modal_integrator

    scenario, _ = lqg_model
    model = build_modal_integrator(scenario, DataConfig(frames=2048, dither_nm=5.0, integrator_gain=0.4))
    scan = model.info["margin_scan"]
    assert list(scan) == [f"{m:g}" for m in GAIN_MARGIN_CANDIDATES]
    finite = {m: v for m, v in scan.items() if v is not None}
    assert float(min(finite, key=finite.get)) == model.info["gain_margin"]
    assert float(model.gains.max()) <= model.info["critical_gain"] / model.info["gain_margin"] * (1 + 1e-12)


def test_the_lqg_of_each_ar_order_and_the_modal_integrator_share_one_recording(small_scenario, monkeypatch):
    """Equal scenario, data and DM model: the telemetry is recorded (and its modal statistics computed) once, and
    each model is the one a fresh recording gives."""
    from eofnn.control import modal

    data = DataConfig(frames=1024, dither_nm=5.0)
    modal._RECORDED.clear()
    fresh = {order: build_lqg(small_scenario, data, 20, ar_order=order) for order in (1, 2)}
    modal._RECORDED.clear()
    calls = []
    record = modal.record_pol_telemetry
    monkeypatch.setattr(modal, "record_pol_telemetry", lambda *a, **k: calls.append(1) or record(*a, **k))
    shared = {order: build_lqg(small_scenario, data, 20, ar_order=order) for order in (1, 2)}
    integrator = modal.build_modal_integrator(small_scenario, data, 20)
    assert len(calls) == 1
    for order in (1, 2):
        torch.testing.assert_close(shared[order].kalman_gain, fresh[order].kalman_gain, rtol=0, atol=0)
        assert shared[order].info == fresh[order].info
    torch.testing.assert_close(integrator.modes, shared[2].modes, rtol=0, atol=0)
    build_lqg(small_scenario, DataConfig(frames=1024, dither_nm=6.0), 20)  # other data: recorded again
    assert len(calls) == 2
