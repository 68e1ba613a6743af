"""Per-mode gains from a modal dither (:mod:`eofnn.training.modal_gains`): a pyramid's optical gains identified from
its closed-loop telemetry agree with the probe measurement about the same residual."""

from __future__ import annotations

import json

import pytest
import torch

from eofnn.cli.main import main
from eofnn.control import Dithered, Integrator
from eofnn.errors import ConfigError, TelemetryError
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Telemetry, run_loop
from eofnn.sim.loop.plant import Plant
from eofnn.sim.scenario import Scenario
from eofnn.sim.sensing.optical_gains import OpticalGainProbe, kl_modes, modal_optical_gains
from eofnn.training.modal_gains import identify_modal_gains

ORDERS = [1, 3, 8]


def _record(dither_nm: float, frames: int, orders=ORDERS, dm_gain: float = 2.0) -> Telemetry:
    """12 actuators across 2 m, one 10 m/s layer, two-frame delay, a DM gain of 2, the subaperture sensor; an
    integrator (gain 0.3) plus white dither on the Karhunen-Loeve modes of ``orders``."""
    atmosphere = Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=(Layer(1.0, 10.0, 0.0),))
    sc = Scenario(ActuatorGrid(2.0, 12), atmosphere, 1000.0, Plant(delay_frames=2, dm_gain=dm_gain, wfs_noise_nm=2.0))
    modes = kl_modes(sc.grid, max(orders))[:, [o - 1 for o in orders]]
    result = run_loop(sc.turbulence(0, "identify"), sc.plant, Dithered(Integrator(0.3), dither_nm, 1, modes), frames,
                      noise_seed=2)
    return result.telemetry.realisation(0)


@pytest.fixture(scope="module")
def dithered() -> Telemetry:
    return _record(10.0, 2000)


def test_a_modal_dither_gives_each_modes_gain_with_an_honest_error(dithered):
    found = identify_modal_gains(dithered, ORDERS)
    assert found["orders"] == ORDERS and found["basis"] == "karhunen_loeve"
    for gain, se, excitation in zip(found["gains"], found["gains_se"], found["excitation_rms_nm"], strict=True):
        assert 0 < se < 0.05 and abs(gain - 2.0) < 4 * se + 0.01  # the DM gain, every mode (a linear sensor)
        assert excitation == pytest.approx(10.0, rel=0.1)
    assert found["mean_gain"] == pytest.approx(2.0, abs=0.05)
    # A wfs recorded a frame late, realigned by the lag identify_plant finds: the same gains.
    late = Telemetry(y=dithered.y[1:], wfs=dithered.wfs[:-1], delay_frames=2, positions_m=dithered.positions_m)
    again = identify_modal_gains(late, ORDERS, lag_frames=1)
    assert again["gains"] == pytest.approx(found["gains"], abs=0.005)  # one frame fewer
    assert all(abs(g - 2.0) > 1.0 for g in identify_modal_gains(late, ORDERS)["gains"])  # not realigned: wrong


def test_an_undithered_or_too_weakly_dithered_mode_is_refused_in_one_line(dithered):
    with pytest.raises(TelemetryError, match=r"optical_gain_modes \[2\] carry no dither") as err:
        identify_modal_gains(dithered, [1, 2])
    assert "\n" not in str(err.value)
    weak = _record(0.2, 600)
    with pytest.raises(TelemetryError, match="dithered too weakly .* standard error must be below 10%") as err:
        identify_modal_gains(weak, ORDERS)
    assert "\n" not in str(err.value)
    for bad in ([], [0], [1, 1], [112], [1.5]):
        with pytest.raises(ConfigError, match="optical_gain_modes=.* is invalid: it must be distinct"):
            identify_modal_gains(dithered, bad)
    with pytest.raises(TelemetryError, match="telemetry has 150 frames: optical-gain identification needs at least"):
        identify_modal_gains(Telemetry(y=dithered.y[:150], wfs=dithered.wfs[:150], delay_frames=2,
                                       positions_m=dithered.positions_m), ORDERS)
    bare = Telemetry(y=dithered.y, wfs=dithered.wfs, delay_frames=2)
    with pytest.raises(TelemetryError, match="need actuator-space telemetry with positions"):
        identify_modal_gains(bare, ORDERS)


@pytest.mark.cli
def test_identify_reports_the_modal_gains(dithered, tmp_path, capsys):
    dithered.save(tmp_path / "run.npz")
    assert main(["identify", "--telemetry", str(tmp_path / "run.npz"), "--out", str(tmp_path / "plant.json"),
                 "--optical_gain_modes", "[1, 3, 8]"]) == 0
    plant = json.loads((tmp_path / "plant.json").read_text())
    gains = plant["optical_gains"]
    assert gains["orders"] == ORDERS and len(gains["gains"]) == len(gains["gains_se"]) == 3
    assert all(abs(g - 2.0) < 0.1 for g in gains["gains"])
    assert '"optical_gains"' in capsys.readouterr().err


@pytest.mark.physics
@pytest.mark.slow
def test_a_pyramids_optical_gains_identified_from_telemetry_agree_with_the_probe():
    """A modulated pyramid (8 across 3.2 m, r0 = 15 cm, modulation 3 lambda/D) closed by an integrator (gain 0.5)
    with 30 nm of white dither on five KL modes: about its ~190 nm residual the optical gains are about 0.5, and those
    identified from the telemetry agree with :func:`modal_optical_gains` about the residual of the same run within
    15% per mode (the identified gain is the response in command space, what the loop sees; the probe's is the
    projection in signal space)."""
    frames, orders = 3000, [1, 2, 5, 10, 20]
    sc = Scenario.from_dict({"grid": {"diameter_m": 3.2, "n_across": 8, "obstruction": 0.0},
                             "atmosphere": {"r0_m": 0.15, "layers": [{"wind_speed_mps": 10.0}],
                                            "screen_frames": frames + 10},
                             "plant": {"delay_frames": 2},
                             "sensor": {"kind": "pyramid", "modulation_lambda_over_d": 3, "samples_per_pixel": 4}})
    turbulence = sc.turbulence(1, "test")
    modes = kl_modes(turbulence.grid, max(orders))[:, [o - 1 for o in orders]]
    probe = OpticalGainProbe(turbulence.operators.sensor, 200, frames, n_modes=max(orders), n_frames=12)
    result = run_loop(turbulence, sc.plant, Dithered(Integrator(0.5), 30.0, 3, modes), frames, noise_seed=2,
                      on_chunk=probe)
    assert not result.diverged
    probed, _ = modal_optical_gains(turbulence.operators.sensor, torch.cat(probe.residuals), max(orders))
    probed = probed[[o - 1 for o in orders]]
    assert float(probed.max()) < 0.8  # the pyramid is well away from its linear regime
    found = identify_modal_gains(result.telemetry.realisation(0), orders)
    identified = torch.tensor(found["gains"])
    assert ((identified / probed - 1).abs() < 0.15).all(), (identified, probed)
    assert (torch.tensor(found["gains_se"]) < 0.1 * identified).all()
