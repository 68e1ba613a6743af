"""Physics of the turbulence: structure function against von Kármán theory, frozen flow, the study's numbers."""

from __future__ import annotations

import hcipy
import numpy as np
import pytest
import torch

from eofnn.errors import ConfigError
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Turbulence
from eofnn.sim.atmosphere.strip import FrozenFlowStrip
from eofnn.sim.atmosphere.turbulence import stream_seed
from eofnn.sim.scenario import Scenario


def theory_structure_function_nm2(r_m: np.ndarray, r0_m: float, wavelength_m: float, outer_scale_m: float):
    """Von Kármán phase structure function 2 (C(0) - C(r)) from HCIPy's covariance, in nm² of OPD."""
    cov = hcipy.phase_covariance_von_karman(r0_m, outer_scale_m)
    grid = hcipy.CartesianGrid(hcipy.UnstructuredCoords((np.concatenate([[0.0], r_m]), np.zeros(len(r_m) + 1))))
    c = np.asarray(cov(grid))
    rad2 = 2 * (c[0] - c[1:])
    return rad2 * (wavelength_m / (2 * np.pi) * 1e9) ** 2


@pytest.mark.physics
@pytest.mark.slow
@pytest.mark.parametrize(
    "layers",
    [(Layer(1.0, 20.0, 0.0),), (Layer(1.0, 20.0, 30.0),), (Layer(0.7, 20.0, 0.0), Layer(0.3, 25.0, 120.0))],
    ids=["along-x", "30-degrees", "two-layers"],
)
def test_structure_function_matches_von_karman(layers):
    """Cn² adds over layers, so any profile has the structure function of its total r0."""
    grid = ActuatorGrid(4.0, 20)
    atm = Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=layers, remove_ptt=False,
                     model="strip")
    # 20 m/s at 25 Hz: frames 0.8 m apart, so 60 frames x 12 realisations sample ~200 m of screen.
    s = Turbulence(atm, grid, 25.0, seed=3, stream="physics", n_realisations=12).frames(0, 60)
    maps = grid.to_map(s)  # (B, T, n, n) with NaN off the pupil
    pitches = np.array([1, 2, 3])
    measured = []
    for k in pitches:
        dx = maps[..., :, k:] - maps[..., :, :-k]
        dy = maps[..., k:, :] - maps[..., :-k, :]
        diffs = torch.cat([dx.flatten(), dy.flatten()])
        measured.append(diffs[torch.isfinite(diffs)].pow(2).mean().item())
    theory = theory_structure_function_nm2(pitches * grid.pitch_m, 0.1, 500e-9, 20.0)
    # Interpolation at 30 deg smooths the screen a little; the AR extrusion is exact to a few per cent.
    np.testing.assert_allclose(measured, theory, rtol=0.12)
    # Kolmogorov shape at small separations: D(2r)/D(r) close to 2**(5/3) (less, for the outer scale).
    assert 2.6 < measured[1] / measured[0] < 2 ** (5 / 3) + 0.1


@pytest.mark.physics
def test_frozen_flow_integer_shift_is_exact():
    grid = ActuatorGrid(4.0, 20)
    # 4 m/s at 100 Hz: 0.04 m per frame, so 5 frames move the screen exactly one 0.2 m pitch along +x.
    atm = Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, layers=(Layer(1.0, 4.0, 0.0),), remove_ptt=False,
                     model="strip")
    s = Turbulence(atm, grid, 100.0, seed=1).frames(0, 40)[0]
    maps = grid.to_map(s)
    later, earlier = maps[7:, :, 1:], maps[2:-5, :, :-1]  # s(x, n + 5) = s(x - pitch, n)
    ok = torch.isfinite(later) & torch.isfinite(earlier)
    assert ok.sum() > 1000
    torch.testing.assert_close(later[ok], earlier[ok], rtol=0, atol=1e-9)
    # ...and the screen did move: the unshifted comparison is far off.
    assert (later[ok] - maps[2:-5, :, 1:][ok]).abs().mean() > 10.0


@pytest.mark.physics
@pytest.mark.parametrize("direction", [37.0, 200.0])
def test_frozen_flow_subpixel_translation(direction):
    """Frame n+k at x equals frame n at x - v k dt: one continuous screen, translated."""
    grid = ActuatorGrid(2.0, 10)
    speed, dt, k = 7.3, 1e-3, 11
    angle = np.radians(direction)
    shift = speed * k * dt * np.array([np.cos(angle), np.sin(angle)])
    positions = np.concatenate([grid.positions_m, grid.positions_m - shift])
    strip = FrozenFlowStrip(positions, grid.pitch_m, 0.1, 500e-9, 20.0, speed, direction, dt, 5,
                            stream_seed(0, "t"))
    s = strip.frames(0, 200)
    n = grid.n_actuators
    torch.testing.assert_close(s[k:, :n], s[:-k, n:], rtol=0, atol=1e-8)


@pytest.mark.slow
def test_any_frame_range_and_chunking_give_the_same_frames():
    grid = ActuatorGrid(2.0, 10)
    atm = Atmosphere(layers=(Layer(0.7, 30.0, 10.0), Layer(0.3, 12.0, 250.0)), model="strip")
    whole = Turbulence(atm, grid, 500.0, seed=5, n_realisations=2).frames(0, 900)
    chunked = torch.cat([c for _, c in Turbulence(atm, grid, 500.0, seed=5, n_realisations=2).chunks(900, 77)], 1)
    torch.testing.assert_close(chunked, whole, rtol=0, atol=1e-9)
    late = Turbulence(atm, grid, 500.0, seed=5, n_realisations=2).frames(700, 900)
    torch.testing.assert_close(late, whole[:, 700:], rtol=0, atol=1e-9)
    # Same seed and calls: bit-for-bit.
    again = Turbulence(atm, grid, 500.0, seed=5, n_realisations=2).frames(0, 900)
    assert torch.equal(again, whole)
    # Other seed, other stream, other realisation: different screens.
    other_seed = Turbulence(atm, grid, 500.0, seed=6, n_realisations=2).frames(0, 10)
    other_stream = Turbulence(atm, grid, 500.0, seed=5, stream="train", n_realisations=2).frames(0, 10)
    for other in (other_seed, other_stream):
        assert (other - whole[:, :10]).abs().mean() > 100
    assert (whole[0] - whole[1]).abs().mean() > 100


def test_piston_tip_tilt_removed():
    grid = ActuatorGrid(4.0, 20, obstruction=0.2)
    s = Turbulence(Atmosphere(), grid, 1000.0, seed=0).frames(0, 50)[0]
    basis = torch.as_tensor(grid.ptt_basis())
    assert (s @ basis).abs().max() < 1e-8 * s.abs().max()


@pytest.mark.physics
@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reference_scenario_reproduces_the_study(seed):
    """Uncorrected 1.2-1.8 um and pseudo-integrator 23-26 nm (study: 1534 nm and 24.3 nm)."""
    scenario = Scenario.from_yaml("configs/reference.yaml")
    assert scenario.grid.n_actuators == 1264
    s = scenario.turbulence(seed).frames(0, 3000)[0]
    uncorrected = s.pow(2).mean(-1).sqrt().median().item()
    pseudo_integrator = (s[2:] - s[:-2]).pow(2).mean(-1).sqrt().median().item()
    assert 1200 < uncorrected < 1800
    assert 23 < pseudo_integrator < 26


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: Atmosphere(r0_m=-0.1), "r0_m=-0.1"),
        (lambda: ActuatorGrid(8.0, 0), "n_across=0"),
        (lambda: Atmosphere(interpolation_order=2), "interpolation_order=2"),
        (lambda: Layer(wind_speed_mps=-1.0), "wind_speed_mps=-1.0"),
        (lambda: Scenario.from_dict({"atmosphere": {"r0": 0.1}}), "unknown key.*r0"),
    ],
)
def test_bad_turbulence_parameters_are_rejected_in_one_line(build, match):
    with pytest.raises(ConfigError, match=match) as info:
        build()
    assert "\n" not in str(info.value)
