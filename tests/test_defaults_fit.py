"""Defaults that work together: telemetry training longer than one turbulence screen is recorded in sequences."""

from __future__ import annotations

from dataclasses import replace

from eofnn.data.stream import DataConfig
from eofnn.sim.atmosphere.turbulence import Atmosphere
from eofnn.training.from_telemetry import fit_from_scenario_telemetry, telemetry_sequences


def test_default_telemetry_training_fits_the_default_screen():
    data, screen_frames = DataConfig(truth=False), Atmosphere().screen_frames
    n_sequences, frames, val_frames = telemetry_sequences(data)
    assert frames <= screen_frames and frames <= data.sequence_frames
    assert n_sequences * (frames - val_frames) >= data.frames and n_sequences * val_frames >= data.val_frames
    assert telemetry_sequences(DataConfig(frames=2000, val_frames=400)) == (1, 2400, 400)  # fits: as before


def test_telemetry_training_longer_than_the_screen_runs(small_scenario):
    scenario = replace(small_scenario, atmosphere=replace(small_scenario.atmosphere, screen_frames=700))
    data = DataConfig(frames=1200, val_frames=300, sequence_frames=600, truth=False, integrator_gain=0.3)
    fit = fit_from_scenario_telemetry(scenario, "open_loop", 3, data=data)
    assert fit.info["n_sequences"] == 3 and fit.val_loss is not None and fit.val_loss < fit.train_loss * 10
