"""A checkpoint dropped into another simulator's loop says in one line when that loop's conditions differ from its
training's (eofnn/interop/shift.py): a noise-free-trained predictor in a noisy HCIPy loop names both noise levels."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import torch

from eofnn.data.history import HistorySpec
from eofnn.errors import ShiftWarning
from eofnn.interop.hcipy import HcipyLoop
from eofnn.interop.loop import IntegratorControl, TorchControl, run_closed_loop
from eofnn.interop.shift import telemetry_noise_nm
from eofnn.models.linear import LinearFilter
from eofnn.training.conditions import Conditions
from eofnn.training.fit import TrainedPredictor


def _noise_free_predictor(n_actuators: int, dm_gain: float = 1.0) -> TrainedPredictor:
    """A closed-loop filter (an integrator of gain 0.4 in EOF form) whose checkpoint says: trained at 0 nm of noise."""
    spec = HistorySpec("closed_loop", 1, 2)
    network = LinearFilter(n_actuators, spec.n_taps, "shared").double()
    with torch.no_grad():
        network.weight.copy_(torch.tensor([[1.0, -0.4]], dtype=torch.float64))
    info = {"conditions": Conditions(0.0, dm_gain, (20.0,), "scenario").to_dict()}
    return TrainedPredictor(network, spec, {}, n_actuators, info)


@pytest.fixture(scope="module")
def noisy():
    return HcipyLoop(4, 2.0, wfs_noise_nm=6.0)


def test_a_noise_free_predictor_in_a_noisy_loop_says_so_in_one_line_naming_both_levels(noisy):
    control = TorchControl.from_predictor(_noise_free_predictor(noisy.n_actuators), noisy.delay_frames,
                                          name="clean.ckpt")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        record = run_closed_loop(noisy, control, 400, 3)
        again = run_closed_loop(noisy, control, 400, 4)
    lines = [str(w.message) for w in caught if issubclass(w.category, ShiftWarning)]
    assert len(lines) == 1 and "\n" not in lines[0], lines  # once per controller, not once per run
    assert lines[0].startswith("clean.ckpt in hcipy's loop: trained at 0 nm of WFS noise (scenario), used at ")
    used = float(re.search(r"used at ([\d.e+-]+) nm", lines[0]).group(1))
    assert 4.5 < used < 7.5, lines[0]  # identified from the loop's own telemetry: 6 nm
    assert record.shift == lines and len(again.shift) == 1  # every run keeps its lines


def test_the_same_predictor_in_a_loop_like_its_training_says_nothing():
    clean = HcipyLoop(4, 2.0, wfs_noise_nm=0.0)
    control = TorchControl.from_predictor(_noise_free_predictor(clean.n_actuators), clean.delay_frames)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ShiftWarning)
        assert run_closed_loop(clean, control, 400, 3).shift == []
    # Without recorded conditions (an older checkpoint, or a filter fitted here), nothing is compared.
    assert run_closed_loop(clean, IntegratorControl(0.4), 100, 3).shift == []


def test_a_dm_gain_other_than_trained_for_is_named():
    doubled = HcipyLoop(4, 2.0, dm_gain=2.0)
    control = TorchControl.from_predictor(_noise_free_predictor(doubled.n_actuators), doubled.delay_frames)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShiftWarning)
        shift = run_closed_loop(doubled, control, 200, 3).shift
    assert len(shift) == 1 and "trained for a DM gain of 1" in shift[0] and "used at 2" in shift[0], shift


class _Unstated(HcipyLoop):
    """HCIPy's loop, its noise unstated (as OOPAO's with photon noise): identified from the telemetry."""

    def __init__(self, noise_nm: float) -> None:
        super().__init__(4, 2.0, wind_speed_mps=5.0)
        self.wfs_noise_nm, self._noise_nm = None, noise_nm

    def advance(self, command_nm):
        measurement, rms = super().advance(command_nm)
        return measurement + self._noise_nm * self._rng.standard_normal(len(measurement)), rms

    def reset(self, seed: int) -> None:
        super().reset(seed)
        self._rng = np.random.default_rng(seed + 99)


def test_where_the_loop_does_not_state_its_noise_it_is_identified_from_its_telemetry():
    sim = _Unstated(6.0)
    control = TorchControl.from_predictor(_noise_free_predictor(sim.n_actuators), sim.delay_frames)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShiftWarning)
        shift = run_closed_loop(sim, control, 600, 3).shift
    noise = [line for line in shift if "WFS noise" in line]
    assert len(noise) == 1 and "noise identified from its telemetry" in noise[0], shift
    used = float(re.search(r"used at ([\d.e+-]+) nm", noise[0]).group(1))
    assert 5.0 < used < 7.5, noise[0]  # 6 nm, biased up by turbulence that is not smooth over three frames


def test_the_noise_is_identified_from_the_commands_and_measurements():
    rng = np.random.default_rng(0)
    t = np.arange(2000)[:, None] / 1000.0
    turbulence = 50 * np.sin(2 * np.pi * 3 * t + np.arange(8))  # smooth: its structure function is c l^2
    y = -0.9 * turbulence + rng.standard_normal((2000, 8))
    wfs = turbulence + 2.0 * y + 3.0 * rng.standard_normal((2000, 8))
    assert abs(telemetry_noise_nm(y, wfs, 2.0) - 3.0) < 0.15
    assert telemetry_noise_nm(y[:10], wfs[:10], 2.0) is None
