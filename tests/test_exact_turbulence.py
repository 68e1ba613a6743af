"""Physics of the exact frozen-flow model and of the HCIPy pupil model, against theory and against HCIPy."""

from __future__ import annotations

import dataclasses

import hcipy
import numpy as np
import pytest
import torch
from scipy.signal import welch

from eofnn.errors import ConfigError
from eofnn.seeding import stream_seed
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Turbulence
from eofnn.sim.atmosphere import exact
from eofnn.sim.atmosphere.exact import ExactFrozenFlow, von_karman_psd, wind_axes
from eofnn.sim.atmosphere.strip import NM_PER_SCREEN_UNIT
from eofnn.sim.scenario import Scenario

R0, WAVELENGTH, NM_PER_RAD = 0.1, 500e-9, 500e-9 / (2 * np.pi) * 1e9


def _quadrature(f_max: float, segments: int = 300, order: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on [0, f_max], on log-spaced segments (the spectrum peaks near 0)."""
    edges = np.concatenate([[0.0], np.geomspace(1e-5, f_max, segments)])
    x, w = np.polynomial.legendre.leggauss(order)
    width = np.diff(edges)[:, None]
    return (edges[:-1, None] + width * (x + 1) / 2).ravel(), (width * w / 2).ravel()


def kernel_squared(f_x: np.ndarray, f_y: np.ndarray, pitch_m: float, kernel: str) -> np.ndarray:
    return np.sinc(pitch_m * f_x) ** 2 * np.sinc(pitch_m * f_y) ** 2 if kernel == "subaperture" else 1.0 + 0 * f_x


def theory_structure_nm2(separation_m: np.ndarray, pitch_m: float, kernel: str, outer_scale_m: float):
    """``(variance, D(r))`` in nm²: 4 ∫∫_{f>0} Φ |K|² (1, 2 (1 - cos 2π f_x r)) df_x df_y, by quadrature."""
    f, w = _quadrature(400 / pitch_m)
    fx, fy = f[:, None], f[None, :]
    weight = 4 * von_karman_psd(np.hypot(fx, fy), R0, outer_scale_m) * kernel_squared(fx, fy, pitch_m, kernel)
    weight = weight * w[:, None] * w[None, :] * NM_PER_RAD**2
    structure = [(2 * weight * (1 - np.cos(2 * np.pi * fx * r))).sum() for r in separation_m]
    return weight.sum(), np.array(structure)


def theory_temporal_psd_nm2_per_hz(f_hz: np.ndarray, speed_mps: float, pitch_m: float, kernel: str,
                                   outer_scale_m: float, frame_rate_hz: float, direction_deg: float = 0.0):
    """One-sided PSD of one actuator's frames: (1/v) ∫ Φ(f/v, f_w) |K|² df_w, with the frame rate's aliases.

    ``K`` is the kernel's transform at the telescope-frame frequencies of (along-wind f/v, across-wind f_w).
    """
    fw, ww = _quadrature(400 / pitch_m)
    fw, ww = np.concatenate([-fw[::-1], fw]), np.concatenate([ww[::-1], ww])
    c, s = np.cos(np.radians(direction_deg)), np.sin(np.radians(direction_deg))
    total = 0.0
    for alias in (-2, -1, 0, 1, 2):
        fu = np.abs(f_hz + alias * frame_rate_hz)[:, None] / speed_mps
        k2 = kernel_squared(fu * c - fw[None] * s, fu * s + fw[None] * c, pitch_m, kernel)
        total = total + (von_karman_psd(np.hypot(fu, fw[None]), R0, outer_scale_m) * k2 * ww).sum(1) / speed_mps
    return 2 * total * NM_PER_RAD**2  # one-sided


def exact_atmosphere(layers, outer_scale_m=20.0, kernel="subaperture", screen_frames=4096, remove_ptt=False):
    return Atmosphere(r0_m=R0, r0_wavelength_m=WAVELENGTH, outer_scale_m=outer_scale_m, layers=layers,
                      remove_ptt=remove_ptt, model="exact", kernel=kernel, screen_frames=screen_frames)


@pytest.mark.physics
def test_von_karman_psd_is_hcipys():
    f = np.geomspace(1e-3, 1e3, 50)
    grid = hcipy.CartesianGrid(hcipy.UnstructuredCoords((2 * np.pi * f, np.zeros_like(f))))
    hcipy_psd = np.asarray(hcipy.power_spectral_density_von_karman(R0, 20.0)(grid))
    np.testing.assert_allclose(von_karman_psd(f, R0, 20.0), hcipy_psd, rtol=1e-3)


@pytest.mark.physics
@pytest.mark.slow
@pytest.mark.parametrize("direction", [0.0, 45.0])
def test_temporal_psd_matches_subaperture_frozen_flow_theory_without_comb(direction):
    """Uncorrected s of each actuator: within 15% of theory in log bands 1-300 Hz, and no comb in 4 Hz bands."""
    speed, rate = 10.0, 1000.0
    grid = ActuatorGrid(1.6, 8)
    atm = exact_atmosphere((Layer(1.0, speed, direction),), screen_frames=16384)
    s = Turbulence(atm, grid, rate, seed=0, n_realisations=12).frames(0, 16384).numpy()
    f, measured = welch(s, fs=rate, nperseg=4096, axis=1)
    measured = measured.mean(axis=(0, 2))
    theory = theory_temporal_psd_nm2_per_hz(f, speed, grid.pitch_m, "subaperture", 20.0, rate, direction)
    bands = np.geomspace(1.0, 300.0, 12)
    ratios = [measured[(f >= a) & (f < b)].mean() / theory[(f >= a) & (f < b)].mean()
              for a, b in zip(bands[:-1], bands[1:], strict=True)]
    np.testing.assert_allclose(ratios, 1.0, atol=0.15)
    # A B-spline strip has peaks at multiples of v / pitch = 50 Hz and collapses between them: none here.
    narrow = [measured[(f >= a) & (f < a + 4)].mean() / theory[(f >= a) & (f < a + 4)].mean()
              for a in np.arange(20.0, 300.0, 4.0)]
    assert 0.8 < min(narrow) and max(narrow) < 1.25


@pytest.mark.physics
@pytest.mark.slow
def test_the_b_spline_strip_fails_the_same_comparison():
    """The check above can fail: the strip's piecewise-polynomial series collapse between multiples of v / pitch."""
    speed, rate = 10.0, 1000.0
    grid = ActuatorGrid(1.6, 8)
    atm = Atmosphere(r0_m=R0, r0_wavelength_m=WAVELENGTH, layers=(Layer(1.0, speed, 0.0),), remove_ptt=False,
                     model="strip")
    s = Turbulence(atm, grid, rate, seed=0, n_realisations=2).frames(0, 8192).numpy()
    f, measured = welch(s, fs=rate, nperseg=4096, axis=1)
    theory = theory_temporal_psd_nm2_per_hz(f, speed, grid.pitch_m, "point", 20.0, rate)
    band = (f >= 120) & (f < 124)
    assert measured.mean(axis=(0, 2))[band].mean() < 1e-3 * theory[band].mean()


@pytest.mark.physics
@pytest.mark.slow
@pytest.mark.parametrize(
    "kernel, layers",
    [("subaperture", (Layer(1.0, 20.0, 0.0),)), ("point", (Layer(1.0, 20.0, 0.0),)),
     ("subaperture", (Layer(0.6, 20.0, 90.0), Layer(0.4, 25.0, 180.0))),
     ("subaperture", (Layer(1.0, 20.0, 45.0),)), ("point", (Layer(1.0, 20.0, float(np.degrees(np.arctan2(1, 2)))),))],
    ids=["subaperture", "point", "two-layers", "subaperture-45-degrees", "point-atan-half"],
)
def test_structure_function_and_variance_match_kernel_filtered_theory(kernel, layers):
    """Cn² adds over layers, so any profile has the (kernel-filtered) statistics of its total r0."""
    grid = ActuatorGrid(4.0, 20)
    # 20 m/s at 25 Hz: frames 0.8 m apart; 16 realisations x 60 frames sample ~800 m of screen (~200 outer scales).
    atm = exact_atmosphere(layers, outer_scale_m=4.0, kernel=kernel, screen_frames=60)
    s = Turbulence(atm, grid, 25.0, seed=3, n_realisations=16).frames(0, 60)
    maps = grid.to_map(s)
    pitches = np.array([1, 2, 3])
    measured = []
    for k in pitches:
        diffs = torch.cat([(maps[..., :, k:] - maps[..., :, :-k]).flatten(), (maps[..., k:, :] - maps[..., :-k, :]).flatten()])
        measured.append(diffs[torch.isfinite(diffs)].pow(2).mean().item())
    variance, structure = theory_structure_nm2(pitches * grid.pitch_m, grid.pitch_m, kernel, 4.0)
    np.testing.assert_allclose(measured, structure, rtol=0.06)
    np.testing.assert_allclose(s.pow(2).mean().item(), variance, rtol=0.1)
    if kernel == "point":  # the quadrature itself, against HCIPy's von Kármán covariance
        cov = hcipy.phase_covariance_von_karman(R0, 4.0)
        r = np.concatenate([[0.0], pitches * grid.pitch_m])
        c = np.asarray(cov(hcipy.CartesianGrid(hcipy.UnstructuredCoords((r, np.zeros_like(r))))))
        np.testing.assert_allclose(structure, 2 * (c[0] - c[1:]) * NM_PER_RAD**2, rtol=2e-3)


@pytest.mark.physics
@pytest.mark.parametrize("direction", [0.0, 90.0, 180.0, 270.0])
def test_integer_sample_shift_is_exact(direction):
    """4 m/s at 100 Hz: 5 frames move the screen one pitch, so s(x, n + 5) = s(x - pitch along the wind, n)."""
    grid = ActuatorGrid(4.0, 20)
    atm = exact_atmosphere((Layer(1.0, 4.0, direction),), screen_frames=300)
    maps = grid.to_map(Turbulence(atm, grid, 100.0, seed=1).frames(0, 300)[0])
    axis = -1 if direction in (0.0, 180.0) else -2
    downwind = 1 if direction in (0.0, 90.0) else -1
    later = maps[5:].roll(-downwind, axis)  # the actuator one pitch downwind, 5 frames later
    ok = torch.isfinite(later) & torch.isfinite(maps[:-5])
    edge = [slice(None)] * 3
    edge[axis] = slice(-1, None) if downwind == 1 else slice(0, 1)
    ok[tuple(edge)] = False  # roll wraps the last line round
    assert ok.sum() > 50000
    torch.testing.assert_close(later[ok], maps[:-5][ok], rtol=0, atol=1e-9)
    assert (maps[5:][ok] - maps[:-5][ok]).abs().mean() > 10.0  # ...and the screen did move


@pytest.mark.physics
@pytest.mark.slow
@pytest.mark.parametrize("direction", [45.0, 225.0])
def test_integer_sample_shift_is_exact_along_a_diagonal(direction):
    """5.657 m/s at 100 Hz along 45 degrees: 5 frames move the screen one pitch along x and one along y."""
    grid = ActuatorGrid(4.0, 20)
    speed = np.hypot(0.2, 0.2) / 5 * 100.0
    atm = exact_atmosphere((Layer(1.0, speed, direction),), screen_frames=200)
    maps = grid.to_map(Turbulence(atm, grid, 100.0, seed=4).frames(0, 200)[0])
    downwind = 1 if direction == 45.0 else -1
    later = maps[5:].roll((-downwind, -downwind), (-2, -1))
    ok = torch.isfinite(later) & torch.isfinite(maps[:-5])
    edge = slice(-1, None) if downwind == 1 else slice(0, 1)
    ok[:, edge, :] = False
    ok[:, :, edge] = False
    assert ok.sum() > 30000
    torch.testing.assert_close(later[ok], maps[:-5][ok], rtol=0, atol=1e-9)
    assert (maps[5:][ok] - maps[:-5][ok]).abs().mean() > 10.0


@pytest.mark.slow
def test_fractional_positions_are_the_fourier_series_itself():
    """The non-uniform FFT evaluation equals the direct Fourier sum at each actuator's exact position."""
    grid = ActuatorGrid(2.0, 10)
    layer = ExactFrozenFlow(grid, R0, WAVELENGTH, 20.0, 7.3, 0.0, 1e-3, "point", 2000, stream_seed(0, "t"))
    s = layer.frames(0, 2000)
    u, line, _, _ = wind_axes(grid, 0.0)
    q = np.arange(-layer.n_modes, layer.n_modes + 1)
    deconvolve = 1 / exact.spreading_kernel_transform(q / layer.n_fine)
    errors = []
    for k in (0, 5, 37, 70):
        coefficients = np.fft.ifft(layer._series[line[k]].numpy())[q % layer.n_fine] / deconvolve
        for n in (0, 1, 999, 1999):
            position = n * layer.fine_per_frame + (u.max() - u[k]) / layer.fine_m + exact._SPREAD
            direct = (coefficients * np.exp(-2j * np.pi * q * position / layer.n_fine)).sum().real
            errors.append(abs(direct - s[n, k].item()))
    assert max(errors) < 1e-10 * s.std().item()


@pytest.mark.slow
def test_any_frame_range_and_chunking_give_the_same_frames():
    grid = ActuatorGrid(2.0, 10)
    atm = exact_atmosphere((Layer(0.6, 10.0, 0.0), Layer(0.4, 7.0, 90.0)), screen_frames=5000, remove_ptt=True)
    whole = Turbulence(atm, grid, 1000.0, seed=5, n_realisations=2).frames(0, 5000)
    chunked = torch.cat([c for _, c in Turbulence(atm, grid, 1000.0, seed=5, n_realisations=2).chunks(5000, 777)], 1)
    torch.testing.assert_close(chunked, whole, rtol=0, atol=1e-9)  # PTT projection rounds per chunk
    late = Turbulence(atm, grid, 1000.0, seed=5, n_realisations=2)
    torch.testing.assert_close(late.frames(4100, 4900), whole[:, 4100:4900], rtol=0, atol=1e-9)
    torch.testing.assert_close(late.frames(10, 20), whole[:, 10:20], rtol=0, atol=1e-9)  # and going back
    raw_atm = dataclasses.replace(atm, remove_ptt=False)
    raw = Turbulence(raw_atm, grid, 1000.0, seed=5, n_realisations=2).frames(0, 5000)
    late_raw = Turbulence(raw_atm, grid, 1000.0, seed=5, n_realisations=2).frames(4100, 4900)
    assert torch.equal(late_raw, raw[:, 4100:4900])  # bit for bit before the projection
    assert torch.equal(Turbulence(atm, grid, 1000.0, seed=5, n_realisations=2).frames(0, 5000), whole)
    other_seed = Turbulence(atm, grid, 1000.0, seed=6, n_realisations=2).frames(0, 10)
    other_stream = Turbulence(atm, grid, 1000.0, seed=5, stream="train", n_realisations=2).frames(0, 10)
    for other in (other_seed, other_stream):
        assert (other - whole[:, :10]).abs().mean() > 100
    assert (whole[0] - whole[1]).abs().mean() > 100
    basis = torch.as_tensor(grid.ptt_basis())
    assert (whole @ basis).abs().max() < 1e-8 * whole.abs().max()
    with pytest.raises(ConfigError, match="screen_frames=5000"):
        Turbulence(atm, grid, 1000.0, seed=5).frames(4990, 5001)


@pytest.mark.physics
@pytest.mark.slow
def test_hcipy_pupil_is_hcipys_layer_and_near_theory():
    grid = ActuatorGrid(4.0, 20)
    atm = Atmosphere(r0_m=R0, r0_wavelength_m=WAVELENGTH, outer_scale_m=20.0, layers=(Layer(1.0, 20.0, 30.0),),
                     remove_ptt=False, model="hcipy_pupil")
    turbulence = Turbulence(atm, grid, 25.0, seed=2, n_realisations=8)
    s = turbulence.frames(0, 60)
    # The same layer driven by hand: HCIPy's InfiniteAtmosphericLayer on the pupil grid, t = n dt.
    layer = hcipy.InfiniteAtmosphericLayer(
        hcipy.make_pupil_grid(20, 4.0), hcipy.Cn_squared_from_fried_parameter(R0, WAVELENGTH), 20.0,
        velocity=20.0 * np.array([np.cos(np.radians(30)), np.sin(np.radians(30))]),
        seed=np.random.default_rng(stream_seed(2, "test", 1, 0)))
    direct = []
    for n in range(60):
        layer.t = n * (1 / 25.0)
        direct.append(np.asarray(layer.phase_for(1.0))[grid.mask.ravel()] * NM_PER_SCREEN_UNIT)
    torch.testing.assert_close(s[1], torch.as_tensor(np.array(direct)), rtol=0, atol=1e-9)
    assert torch.equal(turbulence.frames(10, 20), s[:, 10:20])  # going back restarts from frame 0: same frames
    maps = grid.to_map(s)
    measured = [(maps[..., :, k:] - maps[..., :, :-k]).flatten() for k in (1, 2, 3)]
    measured = [m[torch.isfinite(m)].pow(2).mean().item() for m in measured]
    _, structure = theory_structure_nm2(np.array([1, 2, 3]) * grid.pitch_m, grid.pitch_m, "point", 20.0)
    np.testing.assert_allclose(measured, structure, rtol=0.2)


def test_realistic_config_is_exact_with_subapertures():
    scenario = Scenario.from_yaml("configs/realistic.yaml")
    atm = scenario.atmosphere
    assert (atm.model, atm.kernel, atm.remove_ptt, len(atm.layers)) == ("exact", "subaperture", True, 2)
    assert [lay.wind_direction_deg for lay in atm.layers] == [0.0, 90.0]


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: Atmosphere(model="fourier"), "model='fourier'"),
        (lambda: Atmosphere(model="exact", kernel="gaussian"), "kernel='gaussian'"),
        (lambda: Atmosphere(model="strip", kernel="subaperture"), "kernel='subaperture' is invalid for model 'strip'"),
        (lambda: Atmosphere(model="hcipy_pupil", kernel="subaperture"), "for model 'hcipy_pupil'"),
        (lambda: Atmosphere(model="exact", layers=(Layer(1.0, 5.0, float("nan")),)), "wind_direction_deg=nan"),
        (lambda: Atmosphere(model="exact", layers=(Layer(1.0, 0.0, 0.0),)), "wind_speed_mps=0.0"),
        (lambda: Atmosphere(model="exact", outer_scale_m=float("inf")), "outer_scale_m=inf"),
        (lambda: Atmosphere(model="exact", screen_frames=0), "screen_frames=0"),
    ],
)
def test_bad_model_values_are_rejected_in_one_line(build, match):
    with pytest.raises(ConfigError, match=match) as info:
        build()
    assert "\n" not in str(info.value)
