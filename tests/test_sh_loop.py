"""The Shack-Hartmann in eofnn's own loop (:mod:`eofnn.sim.loop.sensing`): the residual over the pupil, the sensor's
noise as it reaches the commands, the fill of the modes the reconstructor cuts, the error budget, raw contrast, and
one-line refusals of what a Shack-Hartmann scenario cannot run."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from eofnn.control.baselines import Integrator, Uncorrected
from eofnn.errors import ConfigError
from eofnn.evaluation.budget import budget_runs, error_budget, fitting_nm, quadrature_difference
from eofnn.evaluation.config import EvaluationConfig
from eofnn.evaluation.contrast import scenario_contrast
from eofnn.sim.loop.runner import run_loop
from eofnn.sim.loop.sensing import PHASE_EVERY, ShackHartmannTurbulence
from eofnn.sim.scenario import Scenario

GRID = {"diameter_m": 4.0, "n_across": 10, "obstruction": 0.0}
ATMOSPHERE = {"r0_m": 0.15, "layers": [{"wind_speed_mps": 10.0}], "screen_frames": 1200}


def _scenario(**sensor) -> Scenario:
    return Scenario.from_dict({"grid": GRID, "atmosphere": ATMOSPHERE, "plant": {"delay_frames": 2},
                               "sensor": {"kind": "shack_hartmann", **sensor}})


@pytest.fixture(scope="module")
def bright():
    return _scenario(detector={"magnitude": 6.0})


def test_the_default_sensor_is_the_zonal_one_and_leaves_the_scenario_as_it_was():
    zonal = Scenario.from_dict({"grid": GRID, "atmosphere": ATMOSPHERE})
    assert not zonal.sensor.is_shack_hartmann
    assert "sensor" not in zonal.to_dict()  # configs written before the sensor existed still match
    assert not isinstance(zonal.turbulence(1, "test"), ShackHartmannTurbulence)
    result = run_loop(zonal.turbulence(1, "test"), zonal.plant, Integrator(0.5), 50, record=())
    assert result.pupil_residual_rms_nm is None


def test_pupil_residual_from_a_few_numbers_per_frame_is_the_direct_one(bright):
    turbulence = bright.turbulence(3, "test")
    ops = turbulence.operators
    phase = turbulence.fine.frames(0, 40)
    out = turbulence.products(0, 40)
    u = torch.randn(1, 40, bright.grid.n_actuators, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    direct = (phase + ops.surface(u[0])[None])[..., ops.pupil]
    direct = (direct - direct.mean(-1, keepdim=True)).pow(2).mean(-1).sqrt()
    fast = ops.pupil_rms(out["z"], out["sum"], out["sumsq"], u)
    torch.testing.assert_close(fast, direct, rtol=1e-9, atol=1e-9)
    # The fit s = P F phi leaves the fitting error: at 0.4 m pitch and r0 = 0.15 m about 0.1 of the phase (Hudgin's
    # 0.23-0.3 (d / r0)^(5/3) rad² for a continuous face-sheet against the PTT-free Kolmogorov phase).
    fit = ops.pupil_rms(out["z"], out["sum"], out["sumsq"], -out["fit"])
    phase_rms = ops.pupil_rms(out["z"], out["sum"], out["sumsq"], torch.zeros_like(u))
    ratio = float((fit / phase_rms).median())
    assert 0.05 < ratio < 0.2


def test_chunks_are_the_same_numbers_cached_or_not_and_the_phase_is_kept_every_tenth_frame(bright):
    a = bright.turbulence(5, "test").products(100, 300)
    b = bright.turbulence(5, "test").products(0, 400)
    for key in ("s", "sensed", "fit", "z", "sum", "sumsq"):
        assert torch.equal(a[key], b[key][:, 100:300])
    turbulence = bright.turbulence(5, "test")
    torch.testing.assert_close(turbulence.phase_at(3 * PHASE_EVERY), turbulence.fine.frames(30, 31)[:, 0])
    with pytest.raises(ConfigError, match="multiples of 10"):
        turbulence.phase_at(31)


def test_noise_reaches_the_commands_as_sigma_squared_r_r_transpose(bright):
    turbulence = bright.turbulence(1, "test")
    sigma = turbulence.slope_noise_nm(0.0)
    ops = turbulence.operators
    # Rousset's photon noise at R = 6 on 0.4 m subapertures at 1 kHz, in nm across a subaperture.
    expected = math.sqrt(bright.sensor.detector.slope_noise_variance_nm2(0.4, 1e-3))
    assert sigma == pytest.approx(expected)
    # In closed loop, the measurement minus its noise-free twin is R n: per-actuator variance sigma² trace(R R^T) / K.
    runs = [run_loop(bright.turbulence(1, "test", isolate=isolate), bright.plant, Integrator(0.4), 600,
                     noise_seed=2, record=("wfs",)) for isolate in ("none", "noise_free")]
    # Same commands are not guaranteed (the loop reacts to the noise): compare the open-loop readings instead.
    s, noisy = turbulence.open_loop(0, 600, bright.plant, torch.Generator().manual_seed(4))
    _, clean = bright.turbulence(1, "test", isolate="noise_free").open_loop(0, 600, bright.plant, None)
    measured = (noisy - clean).pow(2).mean()
    theory = sigma ** 2 * float(ops.reconstructor.pow(2).sum()) / bright.grid.n_actuators
    assert float(measured) == pytest.approx(theory, rel=0.05)
    assert not runs[0].diverged and not runs[1].diverged
    noisy_rms, clean_rms = (float(r.pupil_residual_rms_nm[:, 200:].median()) for r in runs)
    assert noisy_rms > clean_rms


def test_closed_loop_over_the_pupil_sits_above_the_fitting_error_and_budget_terms_add_up():
    bright = _scenario(detector={"magnitude": 11.0})  # faint enough for a noise term well above the scatter
    ev = EvaluationConfig(frames=600, settle_frames=200, seed=1)
    fitting = fitting_nm(bright, ev.seed, "test", ev.frames, ev.settle_frames, 1)
    result = run_loop(bright.turbulence(1, "test"), bright.plant, Integrator(0.5), ev.frames, noise_seed=1, record=())
    total = float(torch.quantile(result.pupil_residual_rms_nm[:, 200:].flatten(), 0.5))
    budget = budget_runs(bright, lambda: Integrator(0.5), ev, total, fitting)
    runs = budget["runs_nm"]
    assert fitting < runs["perfect"] < runs["noise_free"] < total
    for term in ("fitting_nm", "aliasing_nm", "noise_nm", "temporal_nm"):
        assert budget[term] is not None and budget[term] >= 0
    # The terms are quadrature differences of the runs: together they give the total back.
    terms = math.sqrt(sum(budget[k] ** 2 for k in ("fitting_nm", "aliasing_nm", "noise_nm", "temporal_nm")))
    assert terms == pytest.approx(total, rel=1e-9)
    # Uncorrected, the residual is the turbulence itself: no temporal term is smaller than the fitting error's.
    assert fitting < total
    assert error_budget(None, 1.0, 0.5, 0.1)["noise_nm"] is None
    assert quadrature_difference(1.0, 2.0) == 0.0


def test_an_open_loop_filter_per_actuator_holds_because_the_cut_modes_are_filled_with_the_command(bright):
    """The reconstructor cuts waffle and edge modes: a per-actuator command puts something there that the sensor
    never sees. The computer reports its own command in those modes, so `wfs - y` stays the turbulence."""
    turbulence = bright.turbulence(1, "test", isolate="noise_free")
    ops = turbulence.operators
    cut = torch.eye(bright.grid.n_actuators, dtype=torch.float64) - ops.projector
    assert float(torch.linalg.matrix_rank(cut)) >= 1  # there are cut modes

    class Echo:  # y(n) = -POL(n - 2): the pseudo-open-loop "integrator" of the previous measurement, per actuator
        def reset(self, batch, n, delay, dtype):
            self.y = [torch.zeros(batch, n, dtype=dtype) for _ in range(2)]

        def step(self, inp):
            y = -(inp.wfs - self.y[0]) + 1.0 * torch.ones_like(inp.wfs)  # a constant in every actuator, cut modes too
            self.y = [self.y[1], y]
            return y

    result = run_loop(turbulence, bright.plant, Echo(), 300, record=("y", "wfs"), noise_seed=0)
    assert not result.diverged
    pol = result.telemetry.wfs - result.telemetry.y  # the measurement of frame n includes DM(y(n))
    sensed = turbulence.products(0, 300)["sensed"]
    torch.testing.assert_close(pol, sensed, rtol=1e-9, atol=1e-6)


def test_metrics_and_contrast_are_over_the_pupil(bright):
    from eofnn.evaluation.metrics import loop_metrics

    contrast = scenario_contrast(bright, 1.65e-6, 100)
    result = run_loop(bright.turbulence(1, "test"), bright.plant, Integrator(0.5), 400, noise_seed=1, record=(),
                      on_chunk=contrast)
    metrics = loop_metrics(result, 100, 1.65e-6)
    summary = metrics.summary()
    assert summary["residual_over"] == "pupil"
    assert summary["median_rms_nm"] == pytest.approx(float(result.pupil_residual_rms_nm[:, 100:].median()), rel=0.02)
    assert summary["actuator_median_rms_nm"] > 0
    separations, values = contrast.profile()
    assert separations[-1] == pytest.approx(bright.grid.n_across / 2, abs=0.5)
    at = contrast.at()
    assert 0 < at["2"] < 1 and at["3"] is not None
    # Uncorrected, the speckles are brighter at every reported separation.
    open_contrast = scenario_contrast(bright, 1.65e-6, 100)
    run_loop(bright.turbulence(1, "test"), bright.plant, Uncorrected(), 400, record=(), on_chunk=open_contrast)
    assert all(open_contrast.at()[k] > at[k] for k in ("2", "3"))


@pytest.mark.parametrize("sensor, atmosphere, match", [
    ({"subapertures_across": 11, "geometry": "cell"}, {}, "subapertures_across=11 is invalid"),
    ({"detector": {"magnitude": float("nan")}}, {}, "magnitude=nan is invalid"),
    ({"detector": {"magnitude": float("inf")}}, {}, "magnitude=inf is invalid"),
    ({"detector": {"pixels_across": 0}}, {}, "pixels_across=0 is invalid"),
    ({"relative_cut": 1.0}, {}, "removes every mode"),
    ({"samples_per_subaperture": 0}, {}, "samples_per_subaperture=0 is invalid"),
    ({}, {"kernel": "subaperture"}, "kernel='subaperture' is invalid with sensor.kind shack_hartmann"),
    ({}, {"model": "strip"}, "model='strip' is invalid with sensor.kind shack_hartmann"),
    ({"kind": "pyramids"}, {}, "kind='pyramids' is invalid"),
])
def test_bad_sensors_are_one_line(sensor, atmosphere, match):
    with pytest.raises(ConfigError, match=match) as err:
        Scenario.from_dict({"grid": GRID, "atmosphere": {**ATMOSPHERE, **atmosphere},
                            "sensor": {"kind": "shack_hartmann", **sensor}})
    assert "\n" not in str(err.value)


def test_sensor_fields_without_a_shack_hartmann_and_a_reconstructor_that_does_not_fit_are_one_line(bright):
    with pytest.raises(ConfigError, match="invalid for sensor kind 'subaperture'"):
        Scenario.from_dict({"grid": GRID, "sensor": {"detector": {"magnitude": 8}}})
    sensor = bright.turbulence(1, "test").operators.sensor
    with pytest.raises(ConfigError, match="does not fit"):
        sensor.reconstruct(torch.zeros(3, sensor.n_slopes), np.zeros((5, sensor.n_slopes)))


def test_a_nominal_dm_skips_the_projector_and_measures_the_same(bright, monkeypatch):
    from eofnn.sim.loop import sensing

    runs = []
    for fast in (True, False):
        original = sensing.ShackHartmannLoopSensing.__init__

        def init(self, turbulence, model, *args, original=original, fast=fast):
            original(self, turbulence, model, *args)
            self.identity_dm = self.identity_dm and fast

        monkeypatch.setattr(sensing.ShackHartmannLoopSensing, "__init__", init)
        runs.append(run_loop(bright.turbulence(1, "test"), bright.plant, Integrator(0.5), 200, noise_seed=1,
                             record=("wfs",)))
        monkeypatch.setattr(sensing.ShackHartmannLoopSensing, "__init__", original)
    torch.testing.assert_close(runs[0].telemetry.wfs, runs[1].telemetry.wfs, rtol=1e-9, atol=1e-8)


def test_the_sensor_config_repeats_the_shack_hartmann_constants_it_keeps_light():
    from eofnn.sim.sensing import least_squares, sensor, shack_hartmann

    assert sensor.GEOMETRIES == shack_hartmann.GEOMETRIES
    assert sensor.MECHANICAL_COUPLING == least_squares.MECHANICAL_COUPLING
    for name, constraint in shack_hartmann.ShackHartmann._constraints.items():
        assert sensor.Sensor._constraints[name].describe() == constraint.describe()


def test_a_pupil_inside_the_grid_with_partly_lit_subapertures_runs_and_weights_their_noise():
    """OOPAO's geometry in eofnn's loop: the lit pupil 2 m inside 11 x 11 actuators at 0.2 m, the actuators within
    D / 2 + 0.7533 pitch, subapertures at least half lit; the partly lit ones' noise is 1 / lit times larger."""
    scenario = Scenario.from_dict({
        "grid": {"diameter_m": 2.2, "n_across": 11, "active_diameter_m": 2.0 + 2 * 0.7533 * 0.2},
        "atmosphere": ATMOSPHERE, "plant": {"delay_frames": 2},
        "sensor": {"kind": "shack_hartmann", "pupil_diameter_m": 2.0, "lit_fraction": 0.5,
                   "detector": {"magnitude": 6.0}}})
    turbulence = scenario.turbulence(1, "test")
    ops = turbulence.operators
    scale = ops.sensor.slope_noise_scale
    assert scenario.grid.n_actuators == 101 and (scale > 1).any()
    s, noisy = turbulence.open_loop(0, 600, scenario.plant, torch.Generator().manual_seed(4))
    _, clean = scenario.turbulence(1, "test", isolate="noise_free").open_loop(0, 600, scenario.plant, None)
    sigma = turbulence.slope_noise_nm(0.0)
    weighted = sigma ** 2 * float((ops.reconstructor.pow(2) * torch.as_tensor(scale) ** 2).sum()) / 101
    unweighted = sigma ** 2 * float(ops.reconstructor.pow(2).sum()) / 101
    measured = float((noisy - clean).pow(2).mean())
    assert measured == pytest.approx(weighted, rel=0.05) and abs(measured / unweighted - 1) > 0.05
    ev = EvaluationConfig(frames=600, settle_frames=200, seed=1)
    fitting = fitting_nm(scenario, ev.seed, "test", ev.frames, ev.settle_frames, 1)
    result = run_loop(turbulence, scenario.plant, Integrator(0.4), ev.frames, noise_seed=1, record=())
    assert not result.diverged and fitting < float(result.pupil_residual_rms_nm[:, 200:].median()) < 200.0
