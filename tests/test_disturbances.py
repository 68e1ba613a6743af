"""Telescope vibrations and boiling layers: their spectra and statistics against theory, their errors, and the
result they exist for (an integrator leaves a vibration peak that a predictor trained on it removes)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yaml
from scipy.signal import welch

from eofnn.control.baselines import Integrator
from eofnn.data.stream import DataConfig
from eofnn.errors import ConfigError
from eofnn.evaluation.metrics import WelchPSD
from eofnn.seeding import stream_seed
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Plant, run_loop
from eofnn.sim.atmosphere.disturbances import MODES, BoilingLayer, Vibration, VibrationSeries, mode_shape
from eofnn.sim.scenario import Scenario
from eofnn.training.fit import fit_predictor

RATE = 1000.0
GRID = ActuatorGrid(2.0, 10)
FROZEN = (Layer(1.0, 10.0, 0.0),)


def _scenario(vibrations=(), layers=FROZEN, remove_ptt=False, r0_m=0.1, **plant) -> Scenario:
    """A 2 m telescope, 10 actuators across: a small outer scale (5 m) keeps the exact screens small and fast."""
    atmosphere = Atmosphere(r0_m=r0_m, r0_wavelength_m=500e-9, outer_scale_m=5.0, layers=list(layers), model="exact",
                            kernel="subaperture", screen_frames=4096, remove_ptt=remove_ptt)
    return Scenario(grid=GRID, atmosphere=atmosphere, frame_rate_hz=RATE, plant=Plant(delay_frames=2, **plant),
                    vibrations=list(vibrations))


@pytest.mark.physics
def test_modes_are_zernikes_of_unit_rms_over_the_pupil():
    x, y = GRID.positions_m.T
    assert np.allclose(mode_shape(GRID, "tip"), x / np.sqrt(np.mean(x**2)))
    assert np.allclose(mode_shape(GRID, "tilt"), y / np.sqrt(np.mean(y**2)))
    for mode in MODES:
        shape = mode_shape(GRID, mode)
        assert abs(shape.mean()) < 1e-12 and abs(np.mean(shape**2) - 1) < 1e-12
    r2 = x**2 + y**2
    assert np.allclose(mode_shape(GRID, "focus"), (r2 - r2.mean()) / np.std(r2))


@pytest.mark.physics
@pytest.mark.parametrize("damping", [0.0, 0.05])
def test_vibration_psd_peaks_at_its_frequency_with_its_rms(damping):
    vib = Vibration("tip", frequency_hz=40.0, amplitude_nm=30.0, damping=damping)
    frames, realisations = 32768, 8
    k = int(np.argmax(mode_shape(GRID, "tip")))  # an actuator at the rim of the pupil
    weight = mode_shape(GRID, "tip")[k]
    psds = []
    for r in range(realisations):
        series = VibrationSeries([vib], GRID, 1 / RATE, stream_seed(5, "vibration:test", r))
        s = series.add_to(torch.zeros(frames, GRID.n_actuators, dtype=torch.float64), 0, frames)[:, k].numpy()
        f, psd = welch(s, fs=RATE, nperseg=4096)
        psds.append(psd)
    psd = np.mean(psds, axis=0)
    half_width = max(damping * 40.0, f[1])  # the peak's half width at half maximum, at least one bin
    assert abs(f[np.argmax(psd)] - 40.0) <= half_width
    band = np.abs(f - 40.0) < 10 * half_width
    # Narrow band: the power is in the peak (a Lorentzian holds 2 atan(10) / pi = 94% within 10 half widths).
    assert psd[band].sum() > 0.9 * psd.sum()
    rms = math.sqrt(psd.sum() * f[1]) / abs(weight)
    assert rms == pytest.approx(30.0, rel=0.05)


def test_vibrations_add_to_the_turbulence_after_the_ptt_projection_and_reproduce_in_any_chunking():
    vibs = [Vibration("tip", 40.0, 30.0, 0.01), Vibration("focus", 73.0, 10.0, 0.0)]
    plain, vibrating = _scenario(remove_ptt=True), _scenario(vibs, remove_ptt=True)
    s0 = plain.turbulence(3, "test", 2).frames(0, 4096)
    turbulence = vibrating.turbulence(3, "test", 2)
    s = turbulence.frames(0, 4096)
    coefficients = VibrationSeries(vibs, GRID, 1 / RATE, stream_seed(3, "vibration:test", 1)).coefficients(0, 4096)
    modes = torch.as_tensor(np.stack([mode_shape(GRID, v.mode) for v in vibs]))
    assert torch.allclose(s[1] - s0[1], coefficients @ modes, atol=1e-9)  # the tip is seen despite remove_ptt
    # Any range, in any order, in any chunking (the oscillator's state crosses 4096-frame blocks).
    fresh = VibrationSeries(vibs, GRID, 1 / RATE, stream_seed(3, "vibration:test", 1))
    late, early = fresh.coefficients(3000, 4096), fresh.coefficients(0, 1500)
    assert torch.equal(torch.cat([early, fresh.coefficients(1500, 3000), late]), coefficients)
    long = VibrationSeries(vibs, GRID, 1 / RATE, stream_seed(3, "vibration:test", 1))
    chunked = torch.cat([long.coefficients(a, a + 1000) for a in range(0, 10000, 1000)])
    assert torch.equal(VibrationSeries(vibs, GRID, 1 / RATE, stream_seed(3, "vibration:test", 1)).coefficients(
        7000, 10000), chunked[7000:])
    assert not torch.equal(vibrating.turbulence(3, "train:0").frames(0, 10), vibrating.turbulence(3).frames(0, 10))
    assert vibrating.to_dict()["vibrations"][0] == {"mode": "tip", "frequency_hz": 40.0, "amplitude_nm": 30.0,
                                                    "damping": 0.01}


@pytest.mark.parametrize("vibration, message", [
    ({"frequency_hz": 500.0}, "frequency_hz=500.0 is invalid"),
    ({"frequency_hz": 0.0}, "frequency_hz=0.0 is invalid"),
    ({"frequency_hz": -3.0}, "frequency_hz=-3.0 is invalid"),
    ({"amplitude_nm": -1.0}, "amplitude_nm=-1.0 is invalid"),
    ({"damping": 1.0}, "damping=1.0 is invalid"),
    ({"damping": -0.1}, "damping=-0.1 is invalid"),
    ({"mode": "piston"}, "mode='piston' is invalid"),
    ({"phase": 1.0}, "unknown key(s) phase in vibration"),
])
def test_bad_vibrations_are_one_line_errors_naming_the_value(vibration, message):
    config = _scenario().to_dict()
    config["vibrations"] = [{"mode": "tip", "frequency_hz": 40.0, "amplitude_nm": 10.0, **vibration}]
    with pytest.raises(ConfigError) as err:
        Scenario.from_dict(config)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_bad_boiling_is_a_one_line_error():
    with pytest.raises(ConfigError, match=r"boiling_time_s=-0.1 is invalid") as err:
        Layer(1.0, 10.0, 0.0, boiling_time_s=-0.1)
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match=r"boiling_time_s=0.05 is invalid for model 'strip'"):
        Atmosphere(model="strip", layers=[Layer(boiling_time_s=0.05)])
    assert Atmosphere(model="strip", layers=[Layer(boiling_time_s=0.0)]).layers[0].boiling_time_s == 0.0  # frozen


@pytest.mark.slow
@pytest.mark.physics
def test_boiling_keeps_the_variance_and_decorrelates_as_exp_minus_t_over_tau():
    tau_frames, frames, realisations = 20, 4096, 4
    layers = [Layer(1.0, 10.0, 0.0, boiling_time_s=tau_frames / RATE)]
    boiling = _scenario(layers=layers, remove_ptt=True).turbulence(7, "test", realisations)
    s_boil = boiling.frames(0, frames)
    # The construction: the frozen layer of the same seed and a second realisation, mixed by the walk's angle.
    basis = torch.as_tensor(GRID.ptt_basis())
    screens = [strips[0]._screens for strips in boiling._strips]
    assert all(isinstance(strips[0], BoilingLayer) for strips in boiling._strips)
    assert torch.equal(screens[0][0].frames(0, frames, basis), _scenario(remove_ptt=True).turbulence(7).frames(
        0, frames)[0])
    s_frozen = torch.stack([torch.stack([screen.frames(0, frames, basis) for screen in pair]) for pair in screens])
    # Every frame has the frozen layer's statistics: the mean spatial variance agrees.
    var_frozen, var_boil = s_frozen.pow(2).mean(), s_boil.pow(2).mean()
    assert float(var_boil / var_frozen) == pytest.approx(1.0, abs=0.05)
    # The temporal covariance is the frozen flow's times exp(-lag / tau): exp(-1) at lag tau.
    for lag in (10, tau_frames, 40):
        c_frozen = (s_frozen[..., lag:, :] * s_frozen[..., :-lag, :]).mean() / var_frozen
        c_boil = (s_boil[:, lag:] * s_boil[:, :-lag]).mean() / var_boil
        assert float(c_boil / c_frozen) == pytest.approx(math.exp(-lag / tau_frames), abs=0.05), lag
    # The angle's walk alone, over many frames: E cos(theta(n + lag) - theta(n)) = exp(-lag / tau).
    walk = boiling._strips[0][0].angle(0, 400_000)
    for lag in (5, 20, 60):
        assert np.cos(walk[lag:] - walk[:-lag]).mean() == pytest.approx(math.exp(-lag / tau_frames), abs=0.02)


@pytest.mark.slow
@pytest.mark.physics
def test_an_integrator_leaves_the_vibration_peak_that_a_predictor_removes():
    """The on-sky problem predictive control is used for: a 40 Hz tip vibration in weak turbulence."""
    scenario = _scenario([Vibration("tip", 40.0, 30.0, 0.01)], r0_m=0.3)
    fit = fit_predictor(scenario, "open_loop", 12, data=DataConfig(frames=4000, val_frames=1000,
                                                                    sequence_frames=2000, seed=1))
    peak, rms = {}, {}
    for name, controller in (("integrator", Integrator(0.6)), ("predictor", fit.predictor.controller())):
        psd = WelchPSD(512, RATE, settle_frames=500)
        result = run_loop(scenario.turbulence(2), scenario.plant, controller, 4096, record=(), on_chunk=psd)
        f, p = map(np.asarray, psd.result())
        peak[name] = p[np.abs(f - 40.0) <= f[1]].max()
        rms[name] = float(result.residual_rms_nm[:, 500:].median())
    assert peak["predictor"] < 0.01 * peak["integrator"]
    assert rms["predictor"] < 0.3 * rms["integrator"]


@pytest.mark.slow
@pytest.mark.cli
def test_the_cli_runs_vibrations_and_boiling_from_yaml_and_refuses_bad_ones_in_one_line(tmp_path, capsys):
    from eofnn.cli.main import main
    from eofnn.sim import Telemetry

    scenario = _scenario([Vibration("focus", 100.0, 20.0, 0.0)],
                         layers=[Layer(1.0, 10.0, 0.0, boiling_time_s=0.02)]).to_dict()
    (tmp_path / "scenario.yaml").write_text(yaml.safe_dump(scenario))
    out = tmp_path / "run.npz"
    args = ["simulate", "--scenario", str(tmp_path / "scenario.yaml"), "--predictor.controller", "uncorrected",
            "--frames", "300", "--out", str(out)]
    assert main(args) == 0
    capsys.readouterr()
    s = Telemetry.load(out).s
    expected = Scenario.from_dict(scenario).turbulence(1).frames(0, 300)[0]  # simulate's default seed
    assert torch.allclose(s, expected, atol=1e-9)  # the file's scenario: the boiling layer and the vibration
    bad = ["--scenario.vibrations", "[{mode: tip, frequency_hz: 700, amplitude_nm: 5}]"]
    assert main(args[:3] + bad + args[3:] + ["--overwrite", "true"]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert errors == ["eofnn: error: frequency_hz=700.0 is invalid: a vibration must be below the Nyquist frequency "
                      "frame_rate_hz / 2 = 500 Hz"]
