"""eofnn inside an HCIPy loop (eofnn/interop/hcipy.py): a 10 x 10 Fried DM of Gaussian influence functions on 2 m,
applying 2x the command, phase-projection sensor with 2 nm of noise, 1 kHz, two-frame delay."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.interop.hcipy import HcipyLoop
from eofnn.interop.loop import FilterControl, IntegratorControl, TorchControl, run_closed_loop, runtime_filter
from eofnn.models.linear import LinearFilter
from eofnn.runtime import PredictiveFilter
from eofnn.sim.layout import ActuatorLayout
from eofnn.studies.study import StudyConfig, run_study

CONFIG = StudyConfig(record_frames=3000, val_frames=600, heldout_frames=1200, loop_frames=1200, settle_frames=200,
                     warmup_frames=100, gains=(0.3, 0.35, 0.4, 0.45),
                     integrated_modes=())  # the split is tested in OOPAO's loop (test_interop_oopao.py)


@pytest.fixture(scope="module")
def sim() -> HcipyLoop:
    return HcipyLoop(10, 2.0, dm_gain=2.0, wfs_noise_nm=2.0)


@pytest.fixture(scope="module")
def study(sim):
    return run_study(sim, CONFIG, dm_gain_true=2.0).summary()


def test_the_dm_is_a_fried_layout_in_metres(sim):
    layout = ActuatorLayout(sim.positions_m)
    assert sim.n_actuators == 101 and np.isclose(layout.pitch_m, 0.2) and layout.kind == "square"
    assert np.isclose(np.abs(sim.positions_m).max(), 1.0)  # actuators at the subaperture corners, the rim included


@pytest.mark.slow
def test_telemetry_carries_what_eofnn_needs(sim):
    record = run_closed_loop(sim, IntegratorControl(0.25, dither_nm=10.0), 300, 5)
    telemetry = record.telemetry(start=50)
    assert telemetry.y.shape == (250, 101) and telemetry.delay_frames == 2 and telemetry.frame_rate_hz == 1000.0
    assert torch.equal(telemetry.positions_m, torch.from_numpy(sim.positions_m))
    again = run_closed_loop(sim, IntegratorControl(0.25, dither_nm=10.0), 300, 5)
    assert np.array_equal(record.residual_rms_nm, again.residual_rms_nm)  # seeded: bit-for-bit


@pytest.mark.slow
def test_dm_gain_is_identified_within_two_percent(study):
    assert abs(study["identified"]["dm_gain_error"]) < 0.02
    assert study["identified"]["lag_frames"] == 0


@pytest.mark.slow
def test_replayed_eof_predicts_better_than_the_integrator(study):
    assert study["replay"]["predictor_median_rms_nm"] < 0.7 * study["replay"]["integrator_median_rms_nm"]


@pytest.mark.slow
def test_eof_beats_the_best_gain_integrator_in_hcipys_loop(study):
    assert not study["eof"]["diverged"]
    assert study["eof"]["median_rms_nm"] < 0.97 * study["integrator"]["median_rms_nm"]


def test_torch_controller_and_exported_filter_command_the_same():
    spec = HistorySpec("closed_loop", 3, 2)
    network = LinearFilter(7, spec.n_taps).double()
    with torch.no_grad():
        network.weight.copy_(0.1 * torch.randn(network.weight.shape, generator=torch.Generator().manual_seed(0),
                                               dtype=torch.float64))
    from eofnn.control.predictive import PredictiveController

    runtime, torch_side = FilterControl(runtime_filter(network, spec)), TorchControl(PredictiveController(network, spec), 2)
    runtime.reset(7)
    torch_side.reset(7)
    rng = np.random.default_rng(1)
    for _ in range(20):
        m = rng.standard_normal(7)
        assert np.allclose(runtime.step(m), torch_side.step(m), atol=1e-12)


def test_mismatched_sizes_are_refused_with_one_line(sim):
    with pytest.raises(ConfigError, match=r"command has shape \(100,\): the simulator has 101 actuators"):
        sim.advance(np.zeros(100))
    small = PredictiveFilter(np.zeros((76, 2)), [("y", 1), ("wfs", 2)], 2)
    with pytest.raises(ConfigError, match="the filter has 76 actuators but the simulator has 101") as err:
        run_closed_loop(sim, FilterControl(small), 10, 0)
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="warmup_frames=500 is invalid"):
        StudyConfig(warmup_frames=500, settle_frames=300)


@pytest.mark.cli
@pytest.mark.slow
def test_importing_eofnn_and_the_shared_interop_part_needs_no_oopao():
    import subprocess
    import sys

    code = ("import sys, eofnn, eofnn.interop.loop, eofnn.studies.study, eofnn.interop.hcipy; "
            "print(any(m.split('.')[0] == 'OOPAO' for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_the_integrator_scan_climbs_past_the_top_of_its_grid(sim):
    """A grid whose best gain is its highest is no best-gain integrator: the scan climbs on by the grid's step until
    a gain does worse (or diverges)."""
    from eofnn.interop.loop import scan_integrator

    scan = scan_integrator(sim, (0.3, 0.35), 300, 7, 100)
    tried = sorted(scan["scan"])
    assert tried[:2] == [0.3, 0.35] and len(tried) > 2 and np.allclose(np.diff(tried), 0.05)
    assert scan["gain"] < tried[-1]  # it stopped one step past the best
    last = scan["scan"][tried[-1]]
    assert last is None or last > scan["median_rms_nm"]
