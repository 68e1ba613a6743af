"""Predictive Fourier control (eofnn.control.fourier, frozen_flow, wind): its pieces against closed forms and scipy,
its prediction against the discretisation floor of frozen flow on a sampled grid, its winds against the
simulation's, and its analytic DM-gain margin against closing the loop."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from eofnn.analysis import polynomials as poly
from eofnn.analysis.linear import controller_stability, modal_stability
from eofnn.analysis.stability import LoopSetup
from eofnn.control.baselines import Integrator
from eofnn.control.config import PfcConfig
from eofnn.control.fourier import FourierBasis, FourierPredictor, fft_size, stationary_gain
from eofnn.control.frozen_flow import build_pfc, pfc_from_pol
from eofnn.control.wind import identify_winds
from eofnn.data.config import DataConfig
from eofnn.errors import ConfigError
from eofnn.evaluation.config import PredictorConfig
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.loop.runner import run_loop
from eofnn.sim.scenario import Scenario

F64, C128 = torch.float64, torch.complex128
TINY_SCENARIO = Path(__file__).parent / "conf" / "tiny_scenario.yaml"


def tiny(direction_deg: float = 30.0, **plant) -> Scenario:
    """The tiny scenario (2 m, 10 across, 10 m/s) with its wind off the grid's lattice directions."""
    scenario = Scenario.from_yaml(TINY_SCENARIO)
    layer = replace(scenario.atmosphere.layers[0], wind_direction_deg=direction_deg)
    return replace(scenario, atmosphere=replace(scenario.atmosphere, layers=[layer])).with_plant(**plant)


# -- pieces -------------------------------------------------------------------------------------------------------
def test_fourier_basis_dense_and_fft_agree_and_invert():
    grid = ActuatorGrid(2.0, 10)
    dense, fft = FourierBasis(grid, 2.0, dense=True), FourierBasis(grid, 2.0, dense=False)
    assert dense.size == fft_size(10, 2.0) == 21 and dense.n_modes == 21 * 11
    x = torch.randn(3, grid.n_actuators, dtype=F64, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(dense.forward(x), fft.forward(x), rtol=0, atol=1e-10)
    torch.testing.assert_close(dense.inverse(dense.forward(x)), x, rtol=0, atol=1e-12)  # back then forth: identity
    modes = torch.randn(2, dense.n_modes, dtype=C128, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(dense.inverse(modes), fft.inverse(modes), rtol=0, atol=1e-12)
    torch.testing.assert_close(dense.noise_gain(), fft.noise_gain(), rtol=1e-12, atol=0)
    # The extension is biharmonic: a plane over the pupil extends to a map whose periodic bilaplacian vanishes
    # outside the pupil.
    plane = torch.as_tensor(grid.positions_m[:, 0], dtype=F64)
    extended = dense.extend(plane)
    lap = lambda m: 4 * m - sum(m.roll(s, d) for s in (1, -1) for d in (0, 1))  # noqa: E731
    outside = torch.ones(dense.size**2, dtype=torch.bool)
    outside[dense._pixels] = False
    assert float(lap(lap(extended)).flatten()[outside].abs().max()) < 1e-9


@pytest.mark.parametrize("states", [1, 3])
def test_stationary_gain_solves_the_riccati_equation_of_scipy(states):
    """Closed form (one state) and doubling (several) against scipy's DARE, complex, noisy and noise-free modes."""
    from scipy.linalg import solve_discrete_are

    gen = torch.Generator().manual_seed(2)
    modes = 4
    a = 0.999 * torch.exp(2j * math.pi * torch.rand(modes, states, generator=gen, dtype=F64))
    q = torch.rand(modes, states, generator=gen, dtype=F64) + 0.1
    r = torch.tensor([0.5, 2.0, 1e-3, 10.0], dtype=F64)
    gain, prior = stationary_gain(a, q, r)
    for m in range(modes):
        expected = solve_discrete_are(torch.diag(a[m]).conj().resolve_conj().numpy(), torch.ones(states, 1).numpy(),
                                      torch.diag(q[m]).numpy(), r[m: m + 1].view(1, 1).numpy())
        torch.testing.assert_close(prior[m], torch.as_tensor(expected, dtype=C128), rtol=1e-8, atol=1e-10)
        torch.testing.assert_close(gain[m], prior[m].sum(-1) / (prior[m].sum().real + r[m]), rtol=1e-12, atol=0)


def _toy(delay: float, states: int = 3, modes: int = 3) -> FourierPredictor:
    gen = torch.Generator().manual_seed(3)
    a = 0.99 * torch.exp(2j * math.pi * 0.05 * torch.randn(modes, states, generator=gen, dtype=F64))
    gain, _ = stationary_gain(a, torch.rand(modes, states, generator=gen, dtype=F64), torch.full((modes,), 0.3, dtype=F64))
    return FourierPredictor(FourierBasis(ActuatorGrid(2.0, 4), 1.0), a, gain, delay, dm_gain_model=1.3)


@pytest.mark.parametrize("delay", [2, 1.5, 3])
def test_pfc_polynomials_are_the_filter_it_runs(delay):
    """Per mode, the impulse response of ``N / D`` (what the analysis sees) is the command the filter computes from
    a unit reading, through its POL reconstruction of its own past commands (``z = u - g_model z^-d H y``)."""
    model = _toy(delay)
    d_poly, n_poly = model.polynomials()
    model.reset(1, model.basis.grid.n_actuators, delay, F64)
    d, f = int(delay), delay - int(delay)
    frames = 40
    commands = torch.zeros(frames, model.transition.shape[0], dtype=C128)
    for n in range(frames):
        applied = lambda j, n=n: commands[n - j] if n - j >= 0 else torch.zeros_like(commands[0])  # noqa: E731
        pol = (1.0 if n == 0 else 0.0) - model.dm_gain_model * ((1 - f) * applied(d) + f * applied(d + 1))
        commands[n] = -model.modal_step(pol.unsqueeze(0))[0] / model.dm_gain_model
    expected = torch.zeros_like(commands)  # D y = N u, u a unit impulse
    for n in range(frames):
        acc = n_poly[:, n].clone() if n < n_poly.shape[1] else torch.zeros(d_poly.shape[0], dtype=C128)
        for j in range(1, min(n, d_poly.shape[1] - 1) + 1):
            acc -= d_poly[:, j] * expected[n - j]
        expected[n] = acc
    torch.testing.assert_close(commands, expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("delay, plant_delay", [(2, 2), (1.5, 1.5), (2, 3), (2, 2.5)])
def test_state_space_poles_are_the_roots_of_the_characteristic_polynomial(delay, plant_delay):
    """One state per mode (well-conditioned roots): the closed-loop poles of the state space (what the analysis
    uses) are the roots of ``D - g Q N`` at several DM gains, including a plant delay the filter was not made for."""
    model = _toy(delay, states=1, modes=5)
    d_poly, n_poly = model.polynomials()
    for dm_gain in (0.5, 1.3, 2.4):
        setup = LoopSetup(plant_delay, dm_gain, 0.9, model.dm_gain_model, delay)
        characteristic = poly.add(d_poly, -dm_gain * poly.multiply(setup.plant_polynomial(), n_poly))
        torch.testing.assert_close(model.closed_loop_moduli(dm_gain, 0.9, plant_delay),
                                   poly.max_root_modulus(characteristic), rtol=1e-9, atol=1e-12)


def test_complex_crossings_find_the_gain_where_a_rotated_pole_leaves_the_circle():
    """``1 - g c z^-1`` (``c`` complex of modulus 0.5) has its root ``g c`` on the unit circle at ``g = +-2``,
    at the frequency of ``c``'s angle (reported folded into [0, pi])."""
    c = 0.5 * complex(math.cos(2.0), math.sin(2.0))
    a = torch.tensor([[1.0, 0.0]], dtype=C128)
    b = torch.tensor([[0.0, -c]], dtype=C128)
    rows, gains, omega = poly.real_crossings(a, b)
    assert sorted(gains.tolist()) == pytest.approx([-2.0, 2.0], abs=1e-9)
    assert sorted(omega.tolist()) == pytest.approx([math.pi - 2.0, 2.0], abs=1e-9)


def test_pfc_configs_are_checked_in_one_line():
    PredictorConfig(controller="pfc", pfc={"winds": [[10.0, 30.0, 1.0]], "aliases": 0})
    for config, words in ((dict(controller="pfc", pfc={"winds": [[10.0, 30.0]]}), "pfc.winds"),
                          (dict(controller="pfc", pfc={"alpha": 1.0}), "pfc.alpha=1.0 is invalid"),
                          (dict(controller="pfc", pfc={"lyers": 2}), "unknown key(s) lyers in pfc"),
                          (dict(controller="pfc", modes=10), "modes=10 is for controller: modal_integrator or lqg"),
                          (dict(controller="lqg", pfc={"layers": 1}), "is for controller: pfc, not 'lqg'")):
        with pytest.raises(ConfigError) as err:
            PredictorConfig(**config)
        assert words in str(err.value) and "\n" not in str(err.value)


# -- against theory ------------------------------------------------------------------------------------------------
def shift_floor(basis: FourierBasis, s: torch.Tensor, velocity, frames: int) -> torch.Tensor:
    """The discretisation floor: ``s(n) - P (perfect sub-pixel shift of s(n - frames) by v frames T)``, the shift a
    phase ramp on the FFT of the extended map (read back at the actuators, piston/tip/tilt projected out by ``P``):
    frozen flow as well as the sampled grid can carry it."""
    extended = basis.extend(s[:-frames])
    f = torch.fft.fftfreq(basis.size, d=basis.grid.pitch_m, dtype=F64)
    ramp = torch.exp(-2j * math.pi * (f.view(1, -1) * velocity[0] + f.view(-1, 1) * velocity[1]) * frames * 1e-3)
    shifted = torch.fft.ifft2(torch.fft.fft2(extended) * ramp).real.flatten(-2)[..., basis._pixels]
    ptt = torch.as_tensor(basis.grid.ptt_basis(), dtype=F64)
    return s[frames:] - (shifted - (shifted @ ptt) @ ptt.T)


@pytest.mark.physics
@pytest.mark.slow
def test_noise_free_known_wind_prediction_falls_to_the_discretisation_floor():
    """Pure frozen flow (one layer, 10 m/s at 30 degrees: sub-pixel shifts), known wind, no noise, delay 2: with one
    state per mode the Kalman gain is 1 and the filter is the perfect sub-pixel shift, so the closed-loop residual
    (the prediction error: the POL values are the turbulence) is the discretisation floor of ``shift_floor`` (the
    grid samples a subaperture mean that is not band-limited, the extension does not move with the wind, and
    piston/tip/tilt are removed per frame): here barely below the integrator's residual. With the aliases in each
    mode's state, the filter goes well below it."""
    scenario = tiny(30.0)
    truth = scenario.turbulence(5, "train").frames(0, 1024)
    velocity = (10 * math.cos(math.radians(30)), 10 * math.sin(math.radians(30)))
    config = PfcConfig(winds=[[10.0, 30.0, 1.0]], aliases=0, alpha=0.999999)
    scalar = pfc_from_pol(truth, scenario, config, noise_variance=0.0)
    assert scalar.remove_ptt and float(scalar.kalman_gain.abs().min()) > 0.999
    s = scenario.turbulence(1, "test").frames(0, 1500)[0]
    floor = float(shift_floor(scalar.basis, s, velocity, 2)[300:].pow(2).mean(-1).sqrt().median())
    rms = {}
    for name, controller in (("scalar", scalar),
                             ("aliases", pfc_from_pol(truth, scenario, replace(config, aliases=1), noise_variance=0.0)),
                             ("integrator", Integrator(0.9))):
        run = run_loop(scenario.turbulence(1, "test"), scenario.plant, controller, 1500, record=())
        rms[name] = float(run.residual_rms_nm[0, 302:].median())
    assert rms["scalar"] == pytest.approx(floor, rel=0.01)  # measured: 10.73 nm for both
    assert floor < rms["integrator"] and rms["aliases"] < 0.65 * floor  # measured: integrator 12.3, aliases 6.3 nm


@pytest.fixture(scope="module")
def identified():
    """A PFC built like compare builds it: dithered-integrator telemetry, 5 nm of WFS noise, the wind identified."""
    scenario = tiny(30.0, wfs_noise_nm=5.0)
    return scenario, build_pfc(scenario, DataConfig(frames=2048, dither_nm=5.0, integrator_gain=0.4), PfcConfig(layers=2))


@pytest.mark.physics
@pytest.mark.slow
def test_the_wind_is_identified_from_telemetry(identified):
    """One layer at 10 m/s, 30 degrees (two asked for: the second is dropped), from closed-loop telemetry with noise
    and dither; then, on an 8 m pupil, two layers crossing at right angles (5.1 m/s along x, 10 m/s along y)."""
    _, model = identified
    (layer,) = model.info["layers"]
    assert layer["speed_mps"] == pytest.approx(10.0, rel=0.02) and layer["direction_deg"] == pytest.approx(30, abs=2)
    assert model.info["winds_source"] == "identified from telemetry" and model.info["noise_rms_nm"] == pytest.approx(
        5.0, rel=0.1)
    scenario = Scenario.from_dict({"grid": {"diameter_m": 8.0, "n_across": 16}, "atmosphere": {"layers": [
        {"cn2_fraction": 0.5, "wind_speed_mps": 5.1, "wind_direction_deg": 0.0},
        {"cn2_fraction": 0.5, "wind_speed_mps": 10.0, "wind_direction_deg": 90.0}], "screen_frames": 2048}})
    pol = scenario.turbulence(5, "train").frames(0, 2048)
    layers = sorted(identify_winds(pol, FourierBasis(scenario.grid), 1e-3, 2, 50.0), key=lambda lay: lay["speed_mps"])
    for layer, (speed, direction) in zip(layers, ((5.1, 0.0), (10.0, 90.0)), strict=False):
        assert layer["speed_mps"] == pytest.approx(speed, rel=0.1) and layer["direction_deg"] == pytest.approx(
            direction, abs=5)
        assert layer["weight"] == pytest.approx(0.5, abs=0.1)


@pytest.mark.physics
@pytest.mark.slow
def test_analytic_dm_gain_limit_matches_the_simulated_one(identified):
    """The per-mode analysis (modes taken as decoupled) against closing the loop at increasing DM gain: the upper
    limit bisected in simulation to 1.25% is within 5% of the analytic one. With 5 nm of noise the strongest modes'
    Kalman gains are below 1, and the limit is not the noise-free filter's 2."""
    scenario, model = identified
    result = modal_stability(model, LoopSetup.from_plant(scenario.plant, scenario.frame_rate_hz,
                                                         model.dm_gain_model))
    assert result.stable and len(result.max_root_modulus) == model.basis.n_modes
    upper = result.gain_margin[1]
    assert 2.05 < upper < 4

    def diverges(relative: float) -> bool:
        plant = scenario.with_plant(dm_gain=relative * upper)
        return run_loop(plant.turbulence(1, "test"), plant.plant, replace(model), 2000, noise_seed=1, record=(),
                        divergence_factor=5.0).diverged

    low, high = 0.9, 1.1
    assert not diverges(low) and diverges(high)
    for _ in range(3):
        middle = (low + high) / 2
        low, high = (low, middle) if diverges(middle) else (middle, high)
    assert abs((low + high) / 2 - 1) < 0.05


@pytest.mark.slow
def test_pfc_beats_the_integrator_and_is_analysed_like_every_linear_controller(identified):
    """At 5 nm of noise on the tiny scenario, the identified PFC against integrators of gains 0.6-0.9 (the best);
    its analysis is the modal one, as for the LQG."""
    scenario, model = identified
    rms = {}
    for name, controller in (("pfc", replace(model)), *((g, Integrator(g)) for g in (0.6, 0.8, 0.9))):
        run = run_loop(scenario.turbulence(1, "test"), scenario.plant, controller, 1500, noise_seed=1, record=())
        rms[name] = float(run.residual_rms_nm[0, 300:].median())
    assert rms["pfc"] < 0.85 * min(v for k, v in rms.items() if k != "pfc")  # measured: 12.6 nm against 16.0
    result = controller_stability(PredictorConfig(controller="pfc"), model, scenario)
    assert result.structure == "modal" and result.kind == "open_loop" and result.stable
    assert "spatial Fourier modes" in result.notes[-1]


@pytest.mark.cli
@pytest.mark.slow
def test_eofnn_stability_analyses_the_pfc(tmp_path):
    """``eofnn stability --controller {controller: pfc, ...}`` builds it from telemetry and writes its margins."""
    import json

    from eofnn.cli.main import main

    out = tmp_path / "stab"
    controller = "{controller: pfc, pfc: {winds: [[10.0, 0.0, 1.0]]}, data: {frames: 1024, dither_nm: 5.0}}"
    assert main(["stability", "--scenario", str(TINY_SCENARIO), "--controller", controller, "--out", str(out)]) == 0
    result = json.loads((out / "stability.json").read_text())
    low, high = result["dm_gain_interval"]
    assert result["stable"] and result["structure"] == "modal" and result["groups"] == 21 * 11
    assert low < 0.5 and 1.8 < high < 3 and (out / "stability.png").stat().st_size > 0
