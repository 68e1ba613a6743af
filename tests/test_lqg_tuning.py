"""The LQG tuned as the integrator is: its model (the random walk, whose filter is the pseudo-open-loop integrator,
AR(1), AR(2)) and a scalar on its identified noise variance chosen in the loop on a stream of its own, the scalar on
past its grid's edge; the tuned LQG does not lose to the best-gain integrator beyond scatter in a small
Shack-Hartmann loop; bad values in one line."""

from __future__ import annotations

import pytest
import torch

from eofnn.control.config import (
    LQG_NOISE_SCALES,
    MAX_EXTRA_NOISE_SCALES,
    RANDOM_WALK,
    noise_scale_past_edge,
    scan_lqg_settings,
)
from eofnn.control.kalman import fit_ar, kalman_gain
from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
from eofnn.evaluation.experiment import Experiment
from eofnn.evaluation.results import describe_setting_scan
from eofnn.sim.scenario import Scenario

F64 = torch.float64


def test_the_random_walk_model_takes_its_innovation_from_the_noise_free_structure_function():
    """A random walk of innovation q seen with white noise sigma²: the POL autocovariance over a record has
    C0 - C1 = q / 2 + sigma² (stationary increments), so the fit returns a = (1, 0) and q itself."""
    q, sigma2 = torch.tensor([2.0, 0.5], dtype=F64), torch.tensor([1.0, 0.0], dtype=F64)
    c1 = torch.tensor([100.0, 50.0], dtype=F64)
    autocovariance = torch.stack([c1 + q / 2 + sigma2, c1, c1 - q / 2], 1)
    ar, q_hat = fit_ar(RANDOM_WALK, autocovariance, sigma2)
    torch.testing.assert_close(ar, torch.tensor([[1.0, 0.0], [1.0, 0.0]], dtype=F64))
    torch.testing.assert_close(q_hat, q)
    # Its filter is exponential smoothing: the gain of the state's first entry solves P² / (P + r) = q.
    gain, prior = kalman_gain(ar, q_hat, sigma2 + 1.0)
    p = prior[:, 0, 0]
    torch.testing.assert_close(p.pow(2) / (p + sigma2 + 1.0), q)


def test_the_scan_tries_every_model_with_every_scale_then_goes_past_the_edge_until_it_diverges():
    """Faked residuals: AR(1) keeps improving as its noise scale falls (the scan halves it past the grid, then stops
    when it diverges); AR(2) is best inside the grid (nothing more); the random walk at the top edge (doubled, up to
    the most extra scales)."""
    def fake(order: int, scale: float):
        if order == 1:
            return None if scale < 0.1 else 80 + scale
        if order == 2:
            return 81 + abs(scale - 1)
        return 90 - scale / 100

    scanned = scan_lqg_settings(fake)
    grid = [(order, s) for order in (RANDOM_WALK, 1, 2) for s in LQG_NOISE_SCALES]
    assert list(scanned)[:len(LQG_NOISE_SCALES)] == grid[:len(LQG_NOISE_SCALES)]
    assert set(grid) <= set(scanned)
    assert [s for (o, s) in scanned if o == 1][len(LQG_NOISE_SCALES):] == [0.125, 0.0625]  # 0.0625 diverged
    assert [s for (o, s) in scanned if o == 2] == list(LQG_NOISE_SCALES)
    assert [s for (o, s) in scanned if o == RANDOM_WALK][len(LQG_NOISE_SCALES):] == [
        max(LQG_NOISE_SCALES) * 2.0 ** (i + 1) for i in range(MAX_EXTRA_NOISE_SCALES)]
    assert min((k for k, v in scanned.items() if v is not None), key=scanned.get) == (1, 0.125)
    assert noise_scale_past_edge({1.0: 3.0}) is None  # one scale alone: no edge to go past


@pytest.mark.parametrize("config, expected", [
    ({"controller": "lqg", "noise_scales": [0.0]}, "noise_scales=[0.0] is invalid: 0.0 is not a number > 0"),
    ({"controller": "lqg", "noise_scales": [1, -2]}, "noise_scales=[1, -2] is invalid: -2 is not a number > 0"),
    ({"controller": "lqg", "noise_scales": ["x"]}, "noise_scales=['x'] is invalid: 'x' is not a number > 0"),
    ({"controller": "lqg", "noise_scales": []}, "noise_scales=[] is invalid: give a non-empty list"),
    ({"controller": "lqg", "noise_scale": 0}, "noise_scale=0 is invalid"),
    ({"controller": "lqg", "noise_scale": 1e9}, "noise_scale=1000000000.0 is invalid"),
    ({"controller": "integrator", "noise_scale": 2.0}, "noise_scale=2.0 is for controller: lqg, not 'integrator'"),
    ({"controller": "pfc", "noise_scales": [1.0]}, "noise_scales=[1.0] is for controller: lqg, not 'pfc'"),
    ({"controller": "lqg", "ar_orders": [3]}, "ar_orders=[3] is invalid: 3 is not one of 0, 1, 2"),
])
def test_bad_noise_scales_are_one_line_errors(config, expected):
    with pytest.raises(ConfigError) as err:
        PredictorConfig(**config)
    assert expected in str(err.value) and "\n" not in str(err.value)


def _sh_scenario() -> Scenario:
    """A small Shack-Hartmann loop with photon noise (I = 8), two frames of delay, 20 m/s: the OOPAO study's
    conditions on 8 actuators across."""
    return Scenario.from_dict({
        "grid": {"diameter_m": 1.6, "n_across": 8},
        "atmosphere": {"r0_m": 0.15, "r0_wavelength_m": 5e-7, "outer_scale_m": 25.0, "screen_frames": 2048,
                       "layers": [{"cn2_fraction": 1.0, "wind_speed_mps": 20.0, "wind_direction_deg": 30.0}]},
        "plant": {"delay_frames": 2},
        "sensor": {"kind": "shack_hartmann", "detector": {"magnitude": 8.0}}})


def test_the_tuned_lqg_does_not_lose_to_the_best_gain_integrator_in_a_small_sh_loop():
    """Both tuned on the scan stream; scored on 2 realisations of the test stream. The LQG's scan holds the random
    walk (the pseudo-open-loop integrator) at every noise scale, so it may not lose by more than the scatter."""
    data = {"frames": 1024, "integrator_gain": 0.4, "dither_nm": 10.0, "seed": 7}
    experiment = Experiment(_sh_scenario(), {"nominal": {}}, {
        "integrator": PredictorConfig(controller="integrator", gains=[0.3, 0.4, 0.5], data={"frames": 400}),
        "lqg": PredictorConfig(controller="lqg", ar_orders=[0, 1, 2], noise_scales=[0.25, 1.0, 4.0], data=data)},
        EvaluationConfig(frames=500, settle_frames=100, realisations=2, seed=3, psd_segment_frames=128,
                         analytic_stability=False), log=lambda line: None)
    result = experiment.run()
    scan = result.classical_settings["nominal"]["lqg"]
    assert {e["ar_order"] for e in scan["scanned"]} == {0, 1, 2}
    assert scan["median_rms_nm"] == min(e["median_rms_nm"] for e in scan["scanned"] if e["median_rms_nm"])
    assert "noise x" in describe_setting_scan(scan) or scan["noise_scale"] == 1.0
    lqg, integrator = (result.metrics["nominal"][name] for name in ("lqg", "integrator"))
    lqg_runs, int_runs = torch.tensor(lqg.realisation_median_rms_nm), torch.tensor(
        integrator.realisation_median_rms_nm)
    scatter = float((lqg_runs - int_runs).abs().max()) + 0.02 * float(int_runs.mean())
    assert float(lqg_runs.mean()) <= float(int_runs.mean()) + scatter, (lqg_runs, int_runs, scan)
