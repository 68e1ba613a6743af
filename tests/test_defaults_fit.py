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


def test_modal_and_lqg_defaults_fit_the_default_screen(small_scenario):
    """``{controller: modal_integrator}`` or ``lqg`` on a scenario as written: data.frames (20000 by default) longer
    than the screen (10000) is recorded as realisations of at most screen_frames, with one line saying so."""
    from eofnn.control.modal import within_screen
    from eofnn.sim.scenario import Scenario

    default = Scenario(atmosphere=Atmosphere())
    data, note = within_screen(default, DataConfig())
    assert (data.frames, data.realisations) == (10000, 2) and "recorded as 2 realisation(s) of 10000 frames" in note
    fits = DataConfig(frames=4000)
    assert within_screen(default, fits) == (fits, None)


def test_modal_integrator_longer_than_the_screen_runs(small_scenario, recwarn):
    from eofnn.control.modal import build_lqg

    scenario = replace(small_scenario, atmosphere=replace(small_scenario.atmosphere, screen_frames=1500))
    lqg = build_lqg(scenario, DataConfig(frames=2400, dither_nm=5.0), modes=10)
    assert lqg.info["frames"] == 1200
    assert [str(w.message) for w in recwarn if "exceeds atmosphere.screen_frames=1500" in str(w.message)]
