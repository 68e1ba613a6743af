"""The closed-loop runner, the plant and the baseline controllers against the signal conventions."""

from __future__ import annotations

import io
import math

import pytest
import torch

from eofnn.control import Dithered, Integrator, PseudoIntegrator, Uncorrected, critical_gain
from eofnn.errors import ConfigError
from eofnn.sim import Plant, run_loop
from eofnn.sim.loop.plant import PlantModel


@pytest.mark.slow
def test_pseudo_integrator_convention(small_scenario):
    result = run_loop(small_scenario.turbulence(0, n_realisations=2), small_scenario.plant, PseudoIntegrator(), 300)
    tel = result.telemetry
    torch.testing.assert_close(tel.eps[:, 2:], tel.s[:, 2:] - tel.s[:, :-2], rtol=0, atol=1e-9)
    torch.testing.assert_close(tel.y[:, 2:], -tel.s[:, :-2], rtol=0, atol=0)
    torch.testing.assert_close(tel.wfs, tel.eps)  # perfect sensor
    assert not result.diverged


def test_uncorrected_residual_is_the_turbulence(small_scenario):
    result = run_loop(small_scenario.turbulence(0), small_scenario.plant, Uncorrected(), 100)
    assert torch.equal(result.telemetry.eps, result.telemetry.s)
    torch.testing.assert_close(result.residual_rms_nm, result.turbulence_rms_nm)


def test_integrator_recursion(small_scenario):
    gain, leak = 0.4, 0.01
    tel = run_loop(small_scenario.turbulence(0), small_scenario.plant, Integrator(gain, leak), 50).telemetry
    expected = (1 - leak) * tel.y[:, 9] - gain * tel.wfs[:, 8]
    torch.testing.assert_close(tel.y[:, 10], expected)


@pytest.mark.slow
@pytest.mark.physics
@pytest.mark.parametrize("delay", [1, 2, 3])
def test_integrator_stability_boundary_matches_theory(small_scenario, delay):
    scenario = small_scenario.with_plant(delay_frames=delay)
    k_crit = critical_gain(delay)
    assert k_crit == pytest.approx({1: 2.0, 2: 1.0, 3: 2 * math.sin(math.pi / 10)}[delay])
    stable = run_loop(scenario.turbulence(0), scenario.plant, Integrator(0.9 * k_crit), 2000)
    assert not stable.diverged
    assert stable.residual_rms_nm[0, -500:].max() < stable.turbulence_rms_nm[0, -500:].min()
    unstable = run_loop(scenario.turbulence(0), scenario.plant, Integrator(1.1 * k_crit), 2000)
    assert unstable.diverged
    assert 0 < unstable.diverged_frame < 2000
    # Telemetry stops where it diverged, with nothing non-finite in it.
    assert unstable.telemetry.eps.shape[1] == unstable.diverged_frame
    assert torch.isfinite(unstable.residual_rms_nm).all()


@pytest.mark.slow
@pytest.mark.physics
def test_dm_gain_shifts_the_critical_gain(small_scenario):
    plant = Plant(delay_frames=2, dm_gain=2.0)
    assert run_loop(small_scenario.turbulence(0), plant, Integrator(0.6), 1500).diverged
    assert not run_loop(small_scenario.turbulence(0), plant, Integrator(0.4), 1500).diverged


def test_dither_excites_the_commands(small_scenario):
    plain = run_loop(small_scenario.turbulence(0), small_scenario.plant, Integrator(0.5), 200).telemetry
    dithered = run_loop(small_scenario.turbulence(0), small_scenario.plant,
                        Dithered(Integrator(0.5), 3.0, seed=1), 200).telemetry
    assert 2.0 < (dithered.y - plain.y)[:, 0].std().item() < 4.0
    repeat = run_loop(small_scenario.turbulence(0), small_scenario.plant,
                      Dithered(Integrator(0.5), 3.0, seed=1), 200).telemetry
    assert torch.equal(repeat.y, dithered.y)


def test_plant_model_errors(small_scenario):
    grid = small_scenario.grid
    y = torch.randn(3, grid.n_actuators, dtype=torch.float64) * 100
    torch.testing.assert_close(PlantModel(Plant(dm_gain=2.0), grid).apply_dm(y), 2 * y)
    # A whole-pitch misregistration along x moves every command one actuator to the right.
    shifted = grid.to_map(PlantModel(Plant(misregistration_x=1.0), grid).apply_dm(y))
    original = grid.to_map(y)
    inside = torch.isfinite(shifted[..., 1:]) & torch.isfinite(original[..., :-1])
    torch.testing.assert_close(shifted[..., 1:][inside], original[..., :-1][inside])
    # tanh saturates, quadratic grows.
    big = torch.full((1, grid.n_actuators), 5000.0, dtype=torch.float64)
    assert PlantModel(Plant(nonlinearity="tanh", nonlinearity_scale_nm=1000.0), grid).apply_dm(big).max() < 1000.0
    assert PlantModel(Plant(nonlinearity="quadratic", nonlinearity_scale_nm=1000.0), grid).apply_dm(big).min() > 5000.0
    # WFS noise has the configured RMS and is reproducible.
    model = PlantModel(Plant(wfs_noise_nm=5.0, wfs_gain=0.5), grid)
    eps = torch.zeros(200, grid.n_actuators, dtype=torch.float64)
    noise = model.measure(eps, torch.Generator().manual_seed(0))
    assert noise.std().item() == pytest.approx(5.0, rel=0.05)
    assert torch.equal(noise, model.measure(eps, torch.Generator().manual_seed(0)))
    torch.testing.assert_close(PlantModel(Plant(wfs_gain=0.5), grid).measure(y, None), 0.5 * y)


def test_noisy_loop_is_reproducible(small_scenario):
    scenario = small_scenario.with_plant(wfs_noise_nm=2.0)
    a = run_loop(scenario.turbulence(4), scenario.plant, Integrator(0.5), 100, noise_seed=3).telemetry
    b = run_loop(scenario.turbulence(4), scenario.plant, Integrator(0.5), 100, noise_seed=3).telemetry
    c = run_loop(scenario.turbulence(4), scenario.plant, Integrator(0.5), 100, noise_seed=4).telemetry
    assert torch.equal(a.eps, b.eps)
    assert not torch.equal(a.wfs, c.wfs)
    assert (a.wfs - a.eps).std().item() == pytest.approx(2.0, rel=0.1)


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: Plant(delay_frames=0), "delay_frames=0"),
        (lambda: Plant(nonlinearity="cubic"), "nonlinearity='cubic'"),
        (lambda: Plant().with_errors(dm_gian=2.0), "unknown model error 'dm_gian'"),
        (lambda: Plant(wfs_noise_nm=-1.0), "wfs_noise_nm=-1.0"),
        (lambda: Integrator(gain=-0.1), "gain=-0.1"),
    ],
)
def test_bad_plant_parameters_are_rejected_in_one_line(build, match):
    with pytest.raises(ConfigError, match=match) as info:
        build()
    assert "\n" not in str(info.value)


def test_no_progress_bar_when_not_a_terminal(small_scenario, capsys, monkeypatch):
    monkeypatch.setattr("sys.stderr", io.StringIO())
    run_loop(small_scenario.turbulence(0), small_scenario.plant, Uncorrected(), 50)
    assert "frame" not in capsys.readouterr().err
