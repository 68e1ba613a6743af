"""The anti-aliasing EOF trained in a twin identified from OOPAO's telemetry alone (eofnn/studies/twin_transfer.py):
the path runs on a tiny OOPAO loop whose settings and truth raise when read, and the share of the gap it reports."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pytest

from eofnn.studies.twin_transfer import gap_closed, seen_modes


class _Poisoned(Mapping):
    """A settings dict that fails the test when anything reads it."""

    def _fail(self, *args):
        raise AssertionError("the identified-twin path read the simulator's settings")

    __getitem__ = __iter__ = __len__ = get = keys = items = values = __contains__ = _fail


@pytest.mark.slow
def test_the_identified_twin_path_runs_on_oopaos_record_without_reading_its_settings_or_truth():
    pytest.importorskip("OOPAO")
    from eofnn.interop.oopao import OopaoLoop
    from eofnn.runtime import PredictiveFilter
    from eofnn.studies.twin_transfer import identified_trained

    sim = OopaoLoop(8, 1.6, photon_noise=True, magnitude=8.0, wind_speed_mps=20.0, wind_direction_deg=30.0,
                    dm_gain=2.0)
    settings, sim.settings = sim.settings, _Poisoned()

    def truth(*args):
        raise AssertionError("the identified-twin path read the simulator's truth")

    sim.turbulence_fit_nm = sim.turbulence_opd_nm = sim.describe = truth
    build = identified_trained(record_frames=1300, frames=500, val_frames=100, sequences=1, seed=0)
    runtime, info = build(sim, None)
    sim.settings = settings
    assert isinstance(runtime, PredictiveFilter) and runtime.n_actuators == sim.n_actuators
    assert info["matched"] == sim.n_actuators and info["held"] == 0  # the twin's grid lists OOPAO's actuators
    found = info["identified"]
    assert 1.0 < found["dm_gain"] < 3.0 and found["layers"]  # DM gain 2 x an optical gain below 1
    fastest = max(found["layers"], key=lambda lay: lay["weight"])
    assert abs(fastest["speed_mps"] / 20.0 - 1) < 0.3, found  # the wind, from the telemetry alone
    assert info["record_seed"] == 500 and "no simulator setting" in info["knowledge"]


def test_the_share_of_the_gap_is_in_plain_variance_against_the_best_classical_controller():
    metrics = {"best_classical": "pfc", "best_classical_on_scored": "integrator",
               "contenders": {"pfc": {"realisations_median_rms_nm": [10.0, 10.0]},
                              "integrator": {"realisations_median_rms_nm": [9.0, 11.0]},
                              "eof_antialias": {"realisations_median_rms_nm": [6.0, 8.0]},
                              "twin": {"realisations_median_rms_nm": [8.0, 8.0]},
                              "diverged": {"realisations_median_rms_nm": [8.0, None]}}}
    gap = gap_closed(metrics, "twin")
    assert gap["on_scan"]["share"] == pytest.approx((100 - 64) / (100 - 50))
    assert gap["on_scored"]["share"] == pytest.approx((101 - 64) / (101 - 50))
    assert gap_closed(metrics, "diverged")["on_scan"]["share"] is None
    metrics["contenders"]["eof_antialias"]["realisations_median_rms_nm"] = [10.0, 11.0]  # truth loses to pfc
    assert gap_closed(metrics, "twin")["on_scan"]["share"] is None
    assert "no gap to close" in gap_closed(metrics, "twin")["on_scan"]["why"]


def test_the_seen_modes_span_the_reconstructors_commands():
    rng = np.random.default_rng(0)
    v = np.linalg.qr(rng.standard_normal((12, 5)))[0]
    reconstructor = v @ np.diag([1.0, 2.0, 3.0, 4.0, 5.0]) @ rng.standard_normal((5, 20))
    modes = seen_modes(reconstructor)
    assert modes.shape == (12, 5) and np.allclose(modes @ modes.T @ v, v)
