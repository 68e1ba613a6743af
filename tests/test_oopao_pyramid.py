"""OOPAO's pyramid through the adapter (``OopaoLoop(sensor="pyramid")``, eofnn/interop/oopao_pyramid.py) and against
eofnn's pyramid on the same 8 x 8 system (eofnn/studies/pyramid_compare.py, experiments/pyramid/vs_oopao.py --loop)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("OOPAO")

from eofnn.errors import ConfigError  # noqa: E402
from eofnn.interop.loop import IntegratorControl, run_closed_loop  # noqa: E402
from eofnn.interop.oopao_pyramid import gain_sensing_camera_gains, probe_optical_gains, pyramid_signals  # noqa: E402
from eofnn.studies.pyramid_compare import PyramidSystem, response_ratios, response_with_oopaos_dm  # noqa: E402

SYSTEM = PyramidSystem(n_subapertures=8, diameter_m=2.0)


@pytest.fixture(scope="module")
def built():
    sensor = SYSTEM.eofnn_scenario(200).turbulence(0, "test", 1).operators.sensor
    return sensor, SYSTEM.oopao(200)


def test_the_interaction_matrices_respond_alike_per_kl_mode(built):
    """Per KL command mode, eofnn's pyramid responds as OOPAO's within 10% (median within 5%), and within 1% when
    given OOPAO's own DM surfaces: what is left apart is the DM (OOPAO's influence functions on stretched pixels),
    not the sensor or the units (both in signal per nm of command)."""
    sensor, sim = built
    response = response_ratios(sensor, sim, 100)
    ratio = np.asarray(response["ratio"])
    assert response["modes"] == sim.n_actuators - 1 == 68
    assert response["valid_pixels"]["eofnn"] == response["valid_pixels"]["oopao"]
    assert abs(np.median(ratio) - 1) < 0.05 and np.abs(ratio[:40] - 1).max() < 0.15
    same_dm = np.asarray(response_with_oopaos_dm(sensor, sim, 100))
    assert np.abs(same_dm - 1).max() < 0.01


def test_oopaos_pyramid_closes_the_loop_through_the_adapter(built):
    """The adapter's pyramid: slopes maps of OOPAO's Pyramid, a reconstructor that keeps what the relative cut
    keeps, an integrator loop that corrects (its residual well below the turbulence's), and optical gains below 1
    about the closed-loop residual (of a random probe; per mode, probed and by OOPAO's gain-sensing camera)."""
    _, sim = built
    described = sim.describe()
    assert described["sensor"] == "pyramid" and described["modulation_lambda_over_d"] == 3.0
    assert "modulated pyramid" in described["measurement"] and described["sh_pixels_per_subaperture"] is None
    assert described["n_slopes"] == 2 * int(sim.wfs.validI4Q.sum())  # s_x and s_y on each valid pixel
    maps = []

    def keep(n, sim):
        if n in (120, 149):
            residual = np.zeros(sim.pupil_mask.shape)
            residual[sim.pupil_mask] = sim.residual_opd_nm()
            maps.append(residual)

    record = run_closed_loop(sim, IntegratorControl(0.5), 150, 3, observers=(keep,))
    assert record.metrics(60).median_rms_nm < 0.5 * record.residual_rms_nm[0]
    gain = sim.sensor_gain(record.y[-1], 5.0 * np.random.default_rng(0).standard_normal(sim.n_actuators))
    assert 0.3 < gain < 1.0
    # per mode about the residual maps: push-pull probes and OOPAO's gain-sensing camera (a model) agree
    modes = sim.controlled_modes[:, :10]
    probed = probe_optical_gains(sim, modes, np.asarray(maps)).mean(0)
    modelled = gain_sensing_camera_gains(sim, modes, np.asarray(maps)).mean(0)
    assert ((0.3 < probed) & (probed < 1.0)).all()
    assert np.abs(modelled / probed - 1).max() < 0.1


def test_photon_noise_reaches_the_pyramids_detector(built):
    """With the adapter's photon noise on (``reset`` sets the detector), two reads of the same phase differ; off,
    they are the same."""
    _, sim = built
    flat = np.zeros((2, sim.tel.resolution, sim.tel.resolution))
    try:
        sim.photon_noise = True
        sim.reset(1)
        noisy = pyramid_signals(sim.wfs, flat)
    finally:
        sim.photon_noise = False
        sim.reset(1)
    quiet = pyramid_signals(sim.wfs, flat)
    assert np.abs(noisy[0] - noisy[1]).max() > 1e-3
    assert np.abs(quiet[0] - quiet[1]).max() < 1e-12


def test_the_noise_free_probe_reads_the_optics_gain_under_photon_noise(built):
    """With photon noise on, ``sensor_gain(noise_free=True)`` is the probe read with the detector's noise off (the
    same value as with the loop's noise switched off by hand, twice the same), and the detector's noise is back on
    after it; the noisy probe scatters about it (the example's reference optical gain was read that way)."""
    _, sim = built
    try:
        sim.photon_noise = True
        record = run_closed_loop(sim, IntegratorControl(0.5), 40, 3)
        probe, command = 5.0 * np.random.default_rng(0).standard_normal(sim.n_actuators), record.y[-1]
        clean = [sim.sensor_gain(command, probe, noise_free=True) for _ in range(2)]
        assert sim.wfs.cam.photonNoise
        noisy = [sim.sensor_gain(command, probe) for _ in range(3)]
        sim.wfs.cam.photonNoise = False
        by_hand = sim.sensor_gain(command, probe)
    finally:
        sim.photon_noise = False
        sim.reset(1)
    assert clean[0] == clean[1] == pytest.approx(by_hand, abs=1e-12)
    assert 0.3 < clean[0] < 1.0
    assert np.ptp(noisy) > 1e-3


def test_bad_pyramid_settings_are_refused_in_one_line():
    from eofnn.interop.oopao import OopaoLoop

    with pytest.raises(ConfigError, match=r"^modulation_lambda_over_d=9 is invalid: it must be .*7"):
        OopaoLoop(8, 2.0, pupil_pixels_per_subaperture=2, sensor="pyramid", modulation_lambda_over_d=9)
    with pytest.raises(ConfigError, match=r"photon_noise=True is invalid with sensor='geometric'.*'pyramid'"):
        OopaoLoop(8, 2.0, sensor="geometric", photon_noise=True)
