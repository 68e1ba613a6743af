"""The noise-aware (MMSE) Shack-Hartmann reconstructor (``sensor.reconstructor: mmse``, :mod:`eofnn.sim.sensing.mmse`):
von Kármán's covariance against theory, a better open-loop estimate of the DM's fit than least squares with and
without noise, the loop's measurement kept consistent (``P = R D`` no projector), and the best-gain integrator's pupil
residual against the least-squares one's."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from eofnn.control.baselines import Integrator
from eofnn.errors import ConfigError
from eofnn.sim.loop.runner import run_loop
from eofnn.sim.scenario import Scenario
from eofnn.sim.sensing.mmse import mmse_reconstructor, slope_covariances, von_karman_covariance_nm2
from eofnn.sim.sensing.sensor import Sensor

GRID = {"diameter_m": 2.0, "n_across": 10, "obstruction": 0.0}  # 0.22 m subapertures, 9 x 9 Fried
ATMOSPHERE = {"r0_m": 0.15, "r0_wavelength_m": 5e-7, "outer_scale_m": 20.0, "layers": [{"wind_speed_mps": 10.0}],
              "screen_frames": 410}
FRAMES, SETTLE, GAINS = 400, 200, (0.1, 0.2, 0.3, 0.4, 0.5)


def _scenario(reconstructor: str, magnitude: float | None) -> Scenario:
    sensor = {"kind": "shack_hartmann", "reconstructor": reconstructor}
    if magnitude is not None:
        sensor["detector"] = {"magnitude": magnitude}
    return Scenario.from_dict({"grid": GRID, "atmosphere": ATMOSPHERE, "plant": {"delay_frames": 2},
                               "sensor": sensor})


def test_von_karman_covariance_has_its_variance_and_kolmogorovs_structure_function():
    to_rad2 = (2 * math.pi / 500.0) ** 2  # nm² of OPD to rad² at 500 nm
    # sigma² = 0.0863 (L0 / r0)^(5/3) rad² (Conan 2000); D(r) -> 6.88 (r / r0)^(5/3) for r << L0.
    assert float(von_karman_covariance_nm2(0.0, 1.0, 1.0, 500e-9)) * to_rad2 == pytest.approx(0.0863, rel=1e-3)
    r, r0, outer = 1e-3, 0.1, 1e4
    structure = 2 * (von_karman_covariance_nm2(0.0, r0, outer, 500e-9) - von_karman_covariance_nm2(r, r0, outer, 500e-9))
    assert float(structure) * to_rad2 == pytest.approx(6.88 * (r / r0) ** (5 / 3), rel=0.01)


def test_the_blockwise_covariances_are_the_dense_ones_with_piston_tip_and_tilt_removed():
    scenario = Scenario.from_dict({"grid": {"diameter_m": 1.0, "n_across": 6, "obstruction": 0.0},
                                   "sensor": {"kind": "shack_hartmann", "samples_per_subaperture": 2}})
    ops = scenario.turbulence(0, "test").operators
    geometry = ops.sensor.geometry
    h = geometry.fine_pitch_m
    lattice = np.rint((geometry.fine_positions_m - geometry.fine_positions_m.min(0)) / h).astype(np.int64)
    n = int(lattice.max()) + 1
    table = von_karman_covariance_nm2(np.hypot(*np.meshgrid(np.arange(n), np.arange(n), indexing="ij")) * h,
                                      0.1, 20.0, 5e-7)
    q = geometry.fine_grid.ptt_basis()
    dense = von_karman_covariance_nm2(np.hypot(*(geometry.fine_positions_m[:, None] - geometry.fine_positions_m[None]).T),
                                      0.1, 20.0, 5e-7)
    keep = np.eye(len(q)) - q @ q.T
    dense = keep @ dense @ keep
    s = geometry.slope_operator.toarray()
    fit = ops.influence_pupil_t.toarray()
    signal, cross = slope_covariances(geometry.slope_operator, ops.influence_pupil_t, ops.pupil, lattice, table,
                                      block=7, removed=q)
    np.testing.assert_allclose(signal, s @ dense @ s.T, rtol=1e-9, atol=1e-9 * np.abs(signal).max())
    np.testing.assert_allclose(cross, fit @ dense[ops.pupil] @ s.T, rtol=1e-9, atol=1e-9 * np.abs(cross).max())


def test_the_field_is_checked_and_the_default_leaves_configs_as_they_were():
    assert "reconstructor" not in Sensor(kind="shack_hartmann").to_dict()
    assert Sensor(kind="shack_hartmann", reconstructor="mmse").to_dict()["reconstructor"] == "mmse"
    with pytest.raises(ConfigError, match="reconstructor='wiener'"):
        Sensor(kind="shack_hartmann", reconstructor="wiener")
    with pytest.raises(ConfigError, match="sensor.reconstructor='mmse' is invalid for sensor kind 'subaperture'"):
        Sensor(reconstructor="mmse")
    assert _scenario("least_squares", None).turbulence(1, "test").reconstructor(0.0) is None


def test_the_mmse_estimate_of_the_dms_fit_beats_least_squares_with_and_without_noise():
    scenario = _scenario("mmse", 10.0)
    turbulence = scenario.turbulence(1, "scan")
    ops = turbulence.operators
    out = turbulence.products(0, 300, slopes=True)
    sigma = turbulence.slope_noise_nm(0.0)
    noisy = out["slopes"] + sigma * torch.randn(out["slopes"].shape, generator=torch.Generator().manual_seed(0),
                                                dtype=torch.float64)
    mmse = turbulence.reconstructor(0.0)

    def pupil_nm(slopes, r):
        return float(ops.pupil_rms(out["z"], out["sum"], out["sumsq"], -slopes @ r.T).median())

    for slopes in (out["slopes"], noisy):
        assert pupil_nm(slopes, mmse) < 0.97 * pupil_nm(slopes, ops.reconstructor)
    # More noise, more shrinkage: with 100 times the noise variance the estimate is far smaller.
    signal = torch.eye(4, dtype=torch.float64)
    cross = torch.eye(4, dtype=torch.float64)[:2].numpy()
    torch.testing.assert_close(torch.as_tensor(mmse_reconstructor(signal.numpy(), cross, 1.0)), 0.5 * signal[:2])
    torch.testing.assert_close(torch.as_tensor(mmse_reconstructor(signal.numpy(), cross, 10.0)), signal[:2] / 101)


def test_the_loop_measures_through_the_mmse_reconstructor_consistently():
    scenario = _scenario("mmse", 10.0)
    result = run_loop(scenario.turbulence(2, "test"), scenario.plant, Integrator(0.3), 200, noise_seed=3,
                      record=("s", "y", "wfs", "slopes"))
    tel = result.telemetry
    ops = scenario.turbulence(2, "test").operators
    r, d = tel.reconstructor, tel.interaction_matrix
    torch.testing.assert_close(r, scenario.turbulence(2, "test").reconstructor(0.0))
    p = r @ d
    assert float((p @ p - p).abs().max()) > 1e-3  # no projector
    # The computer's measurement from the slopes, the cut modes filled as with least squares ...
    rebuilt = tel.slopes @ r.T + tel.y - tel.y @ p.T
    assert float((rebuilt - tel.wfs).abs().max()) < 1e-9 * float(tel.wfs.abs().max())
    # ... so that the pseudo-open-loop value wfs - y is R_mmse (S phi + n), whatever the commands: the slopes less D y.
    pol = (tel.slopes - tel.y @ d.T) @ r.T
    torch.testing.assert_close(tel.wfs - tel.y, pol, rtol=0, atol=1e-8 * float(tel.wfs.abs().max()))
    # The truth stays the least-squares sensor's noise-free view.
    truth = scenario.turbulence(2, "test").products(0, 200)["s"]
    torch.testing.assert_close(tel.s, truth)
    assert ops.reconstructor.shape == r.shape


def _best(scenario: Scenario, weight: float = 1.0) -> float:
    best = math.inf
    for gain in GAINS:
        turbulence = scenario.turbulence(1, "scan")
        turbulence.mmse_noise_weight = weight
        result = run_loop(turbulence, scenario.plant, Integrator(gain), FRAMES, noise_seed=7, record=())
        best = min(best, float(result.pupil_residual_rms_nm[:, SETTLE:].median()))
    return best


@pytest.mark.slow
def test_the_best_gain_integrator_does_better_through_the_mmse_reconstructor():
    # No noise: the MMSE prior knows the aliasing; least squares takes it for signal.
    assert _best(_scenario("mmse", None)) < 0.97 * _best(_scenario("least_squares", None))
    # Low flux (R = 13): one frame's noise term over-regularises what the integrator averages over about
    # (2 - g) / g frames; weighted like that average (g / (2 - g) at g = 0.2) the MMSE wins.
    least_squares = _best(_scenario("least_squares", 13.0))
    assert _best(_scenario("mmse", 13.0), weight=0.1) < 0.97 * least_squares


@pytest.mark.cli
@pytest.mark.slow
def test_compare_runs_every_contender_through_the_mmse_reconstructor(tmp_path, cli):
    """``tests/conf/tiny_sh_mmse.yaml``: the best-gain integrator and PFC with the reconstructor's coloured noise, its
    memory scanned on past its grid's edge while the best is there, all measured through the MMSE reconstructor."""
    from eofnn.control.config import alpha_past_edge

    code, err = cli("compare", "--config", Path(__file__).parent / "conf" / "tiny_sh_mmse.yaml", "--out", tmp_path)
    assert code == 0, err
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    runs = metrics["scenarios"]["nominal"]
    assert all(runs[name]["residual_over"] == "pupil" and not runs[name]["diverged"] for name in ("integrator", "pfc"))
    assert metrics["classical_models"]["nominal"]["pfc"]["noise_covariance"] == "coloured (noise_shape)"
    scanned = {e["pfc.alpha"]: e["median_rms_nm"] for e in metrics["classical_settings"]["nominal"]["pfc"]["scanned"]}
    assert list(scanned)[:2] == [0.98, 0.99] and alpha_past_edge(scanned, len(scanned) - 2) is None
    budget = runs["integrator"]["error_budget"]
    assert budget["runs_nm"]["perfect"] < budget["runs_nm"]["noise_free"] < budget["runs_nm"]["total"]
