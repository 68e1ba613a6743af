"""eofnn inside OOPAO's loop (eofnn/interop/oopao.py): a 10 x 10 Shack-Hartmann on 2 m, DM applying 2x the command.

One small study (record with dither -> identify -> fit closed-loop EOF -> refit -> replay -> OOPAO's loop) is run
once for the module; each test checks one thing it must show.
"""

from __future__ import annotations

import numpy as np
import pytest

from eofnn.errors import ConfigError
from eofnn.interop.loop import FilterControl, IntegratorControl, run_closed_loop
from eofnn.interop.oopao import OopaoLoop, measure_sensor_gain
from eofnn.runtime import PredictiveFilter
from eofnn.studies.study import StudyConfig, run_study

CONFIG = StudyConfig(record_frames=2500, val_frames=500, heldout_frames=1000, loop_frames=1000, settle_frames=200,
                     warmup_frames=100, gains=(0.25, 0.3, 0.35), integrated_modes=(0, 6), mixes=(0.5, 1.0))


@pytest.fixture(scope="module")
def sim() -> OopaoLoop:
    return OopaoLoop(10, 2.0, dm_gain=2.0, wind_speed_mps=20.0)


@pytest.fixture(scope="module")
def study(sim):
    return run_study(sim, CONFIG, dm_gain_true=2.0).summary()


def test_the_system_is_a_fried_shack_hartmann(sim):
    info = sim.describe()
    assert info["n_actuators"] == 101 and info["n_slopes"] == 160  # 11 x 11 Fried actuators in the pupil, 80 lenslets
    assert info["sh_pixels_per_subaperture"] >= 4
    pitch = np.sort(np.unique(np.round(sim.positions_m[:, 0], 9)))
    assert np.allclose(np.diff(pitch), 0.2) and np.isclose(pitch.max(), 1.0)  # corners of the 0.2 m subapertures


def test_eofnns_twin_with_oopaos_pupil_has_its_actuators_and_subapertures(sim):
    from eofnn.sim.loop.sensing import loop_operators
    from eofnn.studies.transfer import eofnn_twin, match_positions

    for pupil, missing in (("grid", 4), ("oopao", 0)):  # the grid's pupil lacks 4 of OOPAO's outermost actuators here
        scenario = eofnn_twin(sim, pupil).eofnn_scenario(None, screen_frames=50)
        assert sim.n_actuators - scenario.grid.n_actuators == missing
        match_positions(scenario.grid.positions_m, sim.positions_m)  # each on one of OOPAO's, or one line
    geometry = loop_operators(scenario.grid, scenario.sensor.shack_hartmann()).sensor.geometry
    valid = np.asarray(sim.wfs.valid_subapertures, dtype=bool)
    assert geometry.valid.shape == valid.shape and (geometry.valid == valid).all() and (geometry.valid == valid.T).all()
    assert 0 < (geometry.illumination < 1).sum() < geometry.n_subapertures


@pytest.mark.slow
def test_dm_gain_is_identified_within_two_percent_of_what_telemetry_can_see(sim, study):
    # Telemetry sees the DM gain times the Shack-Hartmann's optical gain (below 1 on a turbulent residual).
    optical = measure_sensor_gain(sim, CONFIG.record_gain, 1000, 0, dither_nm=CONFIG.dither_nm)
    assert 0.85 < optical["mean"] < 1.0
    identified = study["identified"]["dm_gain"]
    assert abs(identified / (2.0 * optical["mean"]) - 1) < 0.02
    assert study["identified"]["lag_frames"] == 0


@pytest.mark.slow
def test_replayed_eof_predicts_better_than_the_integrator(study):
    assert study["replay"]["predictor_median_rms_nm"] < 0.8 * study["replay"]["integrator_median_rms_nm"]


@pytest.mark.slow
def test_eof_beats_the_best_gain_integrator_in_oopaos_loop(study):
    scan = {float(g): v for g, v in study["integrator"]["scan"].items()}
    # The gain is chosen on the scan's own realisation, then scored with the EOF on another one.
    best = min((v, g) for g, v in scan.items() if v is not None)
    assert (study["integrator"]["scan_median_rms_nm"], study["integrator"]["best_gain"]) == best
    assert study["integrator"]["median_rms_nm"] != best[0]
    assert not study["eof"]["diverged"]
    assert study["eof"]["median_rms_nm"] < study["integrator"]["median_rms_nm"]


@pytest.mark.slow
def test_the_split_is_tuned_on_the_scan_realisation_and_beats_the_integrator(study):
    split = study["split"]
    scan = {(int(k.split(", ")[0]), float(k.split(", ")[1])): v for k, v in split["scan"].items()}
    assert set(scan) == {(m, x) for m in (0, 6) for x in (0.5, 1.0)}
    assert split["scan_median_rms_nm"] == min(scan.values()) == scan[split["integrated_modes"], split["mix"]]
    assert split["gain"] == study["integrator"]["best_gain"] and split["n_modes"] == 101
    assert split["median_rms_nm"] < study["integrator"]["median_rms_nm"]
    assert len(split["realisations_median_rms_nm"]) == 1


def test_a_split_that_leaves_the_filter_nothing_is_refused_before_simulating(sim):
    with pytest.raises(ConfigError, match="integrated_modes holds 101: the integrator can keep at most 100"):
        run_study(sim, StudyConfig(integrated_modes=(0, 101)))


def test_mismatched_sizes_are_refused_with_one_line(sim):
    with pytest.raises(ConfigError, match=r"command has shape \(99,\): the simulator has 101 actuators"):
        sim.advance(np.zeros(99))
    small = PredictiveFilter(np.zeros((50, 2)), [("y", 1), ("wfs", 2)], 2)
    with pytest.raises(ConfigError, match="the filter has 50 actuators but the simulator has 101") as err:
        run_closed_loop(sim, FilterControl(small), 10, 0)
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="sensor='curvature' is invalid: it must be one of shack_hartmann, geometric, "
                                          "pyramid, perfect"):
        OopaoLoop(10, 2.0, sensor="curvature")


def test_a_diverging_integrator_is_cut_where_it_diverged(sim):
    record = run_closed_loop(sim, IntegratorControl(1.5), 400, 0)  # loop gain 3 with the 2x DM: unstable
    assert record.diverged_frame is not None and len(record.residual_rms_nm) == record.diverged_frame
    assert record.metrics(10).median_rms_nm is None
