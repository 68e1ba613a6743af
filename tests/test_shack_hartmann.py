"""The geometric Shack-Hartmann core (:mod:`eofnn.sim.sensing.shack_hartmann`): exact slopes of polynomials, the
least-squares reconstructor, noise propagation against the Fourier-domain theory, centroid noise against a Monte
Carlo of a detector, and one-line refusals of bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.special import erf

from eofnn.errors import ConfigError
from eofnn.sim import Atmosphere, Layer, Turbulence
from eofnn.sim.atmosphere.exact import VON_KARMAN_COEFFICIENT
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.sensing.detector import PHOTOMETRY, Detector
from eofnn.sim.sensing.shack_hartmann import ShackHartmann, SubapertureGeometry, default_relative_cut
from eofnn.sim.sensing.subapertures import edge_weights


@pytest.fixture(scope="module")
def sensor10():
    return ShackHartmann().build(ActuatorGrid(4.0, 10))


def _slopes_of(geometry: SubapertureGeometry, phase) -> np.ndarray:
    x, y = geometry.fine_positions_m.T
    return geometry.slope_operator @ phase(x, y)


@pytest.mark.parametrize("kind, m", [("fried", 4), ("fried", 2), ("fried", 3), ("cell", 4), ("cell", 1)])
def test_slopes_of_tilt_defocus_and_a_cubic_are_the_mean_gradient_times_the_side(kind, m):
    grid = ActuatorGrid(4.0, 10, obstruction=0.2)
    geo = SubapertureGeometry(grid, kind, m)
    d = geo.pitch_m
    xc, yc = geo.centres_m.T
    n = geo.n_subapertures
    assert d == pytest.approx(grid.pitch_m)
    # Tilt 30 nm/m in x, -20 nm/m in y: slopes (nm across a subaperture) 30 d and -20 d everywhere.
    s = _slopes_of(geo, lambda x, y: 30 * x - 20 * y)
    np.testing.assert_allclose(s, np.r_[np.full(n, 30 * d), np.full(n, -20 * d)], rtol=0, atol=1e-12)
    # Defocus x² + y² (nm, x in m): mean gradient (2 xc, 2 yc), exact for any edge rule.
    s = _slopes_of(geo, lambda x, y: x ** 2 + y ** 2)
    np.testing.assert_allclose(s, np.r_[2 * xc * d, 2 * yc * d], rtol=0, atol=1e-12)
    # x y²: mean d/dx over the square is <y²> = yc² + d²/12; Simpson's rule is exact for it, the trapezoid is not.
    s = _slopes_of(geo, lambda x, y: x * y ** 2)
    exact = (yc ** 2 + d ** 2 / 12) * d
    if m % 2 == 0:
        np.testing.assert_allclose(s[:n], exact, rtol=0, atol=1e-12)
    else:  # trapezoid: <y²> over m + 1 points is yc² + d² (m + 2) / (12 m)... larger than the true mean
        assert (s[:n] > exact).all()


def test_simpson_weights_and_the_fine_grid_covers_every_edge():
    np.testing.assert_allclose(edge_weights(4), np.array([1, 4, 2, 4, 1]) / 12)
    np.testing.assert_allclose(edge_weights(1), [0.5, 0.5])
    geo = SubapertureGeometry(ActuatorGrid(8.0, 12), "cell", 4)
    # Every column of S that is used holds a fine point in a subaperture; every x row sums to zero (a difference).
    used = np.asarray(abs(geo.slope_operator).sum(0)).ravel() > 0
    assert geo.fine_in_subapertures[used].all()
    np.testing.assert_allclose(np.asarray(geo.slope_operator.sum(1)).ravel(), 0, atol=1e-15)
    assert geo.fine_pitch_m == pytest.approx(geo.pitch_m / 4)
    # The fine grid is an ActuatorGrid whose points lie at -D/2 + i h: subaperture edges fall on them.
    offsets = (geo.fine_positions_m + 4.0) / geo.fine_pitch_m
    np.testing.assert_allclose(offsets, np.round(offsets), atol=1e-9)


def test_influence_functions_have_oopao_shape_and_coupling(sensor10):
    grid, geo = sensor10.grid, sensor10.geometry
    k = int(np.argmin(np.hypot(*grid.positions_m.T)))
    column = sensor10.influence[:, k].toarray().ravel()
    r = np.hypot(*(geo.fine_positions_m - grid.positions_m[k]).T) / grid.pitch_m
    assert column[np.argmin(r)] == pytest.approx(1.0)
    one_pitch = np.isclose(r, 1.0)
    np.testing.assert_allclose(column[one_pitch], 0.35)  # OOPAO's default mechCoupling
    np.testing.assert_allclose(column[column > 0], 0.35 ** (r[column > 0] ** 2))


def test_reconstructor_inverts_the_interaction_matrix_on_the_kept_modes(sensor10):
    s = sensor10
    d, r = s.interaction_matrix, s.reconstructor
    assert d.shape == (s.n_slopes, s.grid.n_actuators) and r.shape == (s.grid.n_actuators, s.n_slopes)
    assert s.relative_cut == 0.1 and default_relative_cut(39) == pytest.approx(3 / 39)
    _, _, vt = np.linalg.svd(d)
    kept = vt[: s.kept_modes].T
    np.testing.assert_allclose(r @ d @ kept, kept, atol=1e-10)  # R D = identity on the controlled modes
    np.testing.assert_allclose(d @ r @ (d @ kept), d @ kept, atol=1e-10)  # D R = identity on their slopes
    # Through the torch boundary: R S (IF y) gives back y for a controlled y.
    y = torch.as_tensor(kept[:, :5].T.copy())
    np.testing.assert_allclose(s.sense(s.dm_surface(y)).numpy(), y.numpy(), atol=1e-9)


def _low_order_errors(sensor) -> list[float]:
    """RMS of ``IF R S phi - phi`` over the sensed area, relative to ``phi``'s, for a tilt, defocus and coma-like
    cubic (piston aside)."""
    x, y = sensor.geometry.fine_positions_m.T
    seen = sensor.geometry.fine_in_subapertures
    errors = []
    for phi in (10 * x, 3 * (x * x + y * y), x * (x * x + y * y)):
        e = (sensor.dm_surface(sensor.sense(torch.as_tensor(phi))).numpy() - phi)[seen]
        errors.append(float((e - e.mean()).std() / phi[seen].std()))
    return errors


def test_fried_reconstructs_low_orders_and_cell_cannot_see_stripes(sensor10):
    """Fried: tilt, defocus and a cubic come back through ``IF R S`` within 12% (5%, 7%, 10% at 10 across). The cell
    geometry does not see a command alternating along x: its surface vanishes on every subaperture edge, so its x
    slopes are zero and its y slopes those of the smooth factor only; a tilt through it keeps 20-40% error."""
    assert max(_low_order_errors(sensor10)) < 0.12
    cell = ShackHartmann(geometry="cell").build(ActuatorGrid(8.0, 16))
    stripes = (-1.0) ** cell.grid.indices[:, 1]
    slopes = (cell.interaction_matrix @ stripes).reshape(2, -1)
    # Away from the rim (where missing actuators break the pattern's symmetry) the slopes vanish ...
    interior = np.hypot(*cell.geometry.centres_m.T) < 4.0 - 4 * cell.grid.pitch_m
    assert interior.sum() >= 12 and np.abs(slopes[:, interior]).max() < 1e-6
    # ... though the DM moves (over 0.5 nm of surface per nm of command).
    assert np.abs(cell.dm_surface(torch.as_tensor(stripes)).numpy()).max() > 0.5
    assert _low_order_errors(cell)[0] > 0.15
    assert cell.geometry.n_subapertures < cell.grid.n_actuators  # the rim's cells are not spanned by the DM


# --- noise propagation --------------------------------------------------------------------------------------------

def fourier_noise_propagation(n: int, relative_cut: float, geometry: str, m: int = 4, coupling: float = 0.35) -> float:
    """Per-actuator command variance per unit white slope-noise variance of the LS reconstructor of a periodic
    ``n x n`` sensor: ``p = (1 / n²) sum_k 1 / |G(k)|²`` over the kept frequencies.

    ``G(k) = (G_x, G_y)`` is the slopes' response to the command pattern ``exp(i k . j d)``: the Gaussian influence
    functions summed over the lattice, read by the same Simpson edge rule on a subaperture centred on an actuator
    (``cell``) or between four (``fried``); frequencies with ``|G| <= cut max |G|`` and piston are dropped (a Fourier
    mode is a singular vector of the periodic ``D``).
    """
    w, t = edge_weights(m), np.linspace(-0.5, 0.5, m + 1)
    c = 0.5 if geometry == "fried" else 0.0
    a = np.fft.fftfreq(n) * 2 * np.pi
    kx, ky = np.meshgrid(a, a)
    j = np.arange(-6, 7)
    jx, jy = (v.ravel() for v in np.meshgrid(j, j))
    phase = np.exp(1j * (kx[..., None] * jx + ky[..., None] * jy))

    def surface(px, py):  # the DM surface at (px, py) pitches from an actuator
        return (phase * coupling ** ((px - jx) ** 2 + (py - jy) ** 2)).sum(-1)

    gx = sum(wi * (surface(c + 0.5, c + ti) - surface(c - 0.5, c + ti)) for wi, ti in zip(w, t, strict=True))
    gy = sum(wi * (surface(c + ti, c + 0.5) - surface(c + ti, c - 0.5)) for wi, ti in zip(w, t, strict=True))
    g = np.sqrt(np.abs(gx) ** 2 + np.abs(gy) ** 2)
    keep = g > relative_cut * g.max()
    keep[0, 0] = False
    return float((1 / g[keep] ** 2).sum() / n ** 2)


@pytest.mark.physics
@pytest.mark.slow
def test_noise_propagation_matches_the_fourier_domain_least_squares_filter():
    """``trace(R R^T) / K`` on a circular pupil against the periodic theory, within 20%: Fried 1.48 against 1.32 at 30
    across, cell 2.13 against 2.17 at 20 (default cut 0.1). The pupil's edge adds ~4 / n (Fried: +42% at 10 across,
    +20% at 20, +13% at 40). The kept modes nearest the cut dominate ``p``: it is no ``0.2 ln n`` law here."""
    for n, geometry in ((30, "fried"), (20, "cell")):
        s = ShackHartmann(geometry=geometry).build(ActuatorGrid(8.0, n))
        theory = fourier_noise_propagation(n, s.relative_cut, geometry)
        assert s.noise_propagation() == pytest.approx(theory, rel=0.2), (n, geometry, s.noise_propagation(), theory)
    # White slope noise through R (the sensor's measure of a flat wavefront): the commands' variance is p sigma².
    s = ShackHartmann().build(ActuatorGrid(8.0, 10))
    flat = torch.zeros(4000, s.geometry.n_fine, dtype=torch.float64)
    measured = float(s.measure(flat, 2.0, torch.Generator().manual_seed(3)).var(0).mean())
    assert measured == pytest.approx(4.0 * s.noise_propagation(), rel=0.05)


# --- aliasing ----------------------------------------------------------------------------------------------------

def fourier_aliasing(pitch_m: float, m: int, relative_cut: float, r0_m: float = 0.1, outer_scale_m: float = 20.0,
                     coupling: float = 0.35, n_k: int = 64, n_aliases: int = 8) -> tuple[float, float]:
    """``(aliasing, fitting)`` variances (rad² at r0's wavelength) of a periodic Fried sensor with Gaussian influence
    functions and its LS reconstructor, for a von Kármán phase.

    At a frequency ``f`` of the DM's band the phase has components ``phi_l`` at ``f_l = f + l / d`` (independent,
    variances ``Phi(f_l)``, the von Kármán PSD); the DM's command pattern ``exp(2 pi i f . j d)`` has surface
    components ``a_l = IF^(f_l) / d²`` (``IF^`` the Gaussian's transform). The DM-projected truth is the
    least-squares fit ``c = sum a_l phi_l / A`` (``A = sum a_l²``); the fitting error is what it leaves,
    ``sum_l Phi_l - sum_l a_l² Phi_l / A``. A Fried subaperture's x slope of ``exp(2 pi i q . x)`` is
    ``(-1)^(l_x + l_y) 2 i sin(pi q_x d) sum_t w_t exp(2 pi i q_y t d)`` (the Simpson edge rule of ``m``), ``g_l``;
    the DM's slopes are ``D = sum g_l a_l`` and the reconstructor ``D^H / |D|²``. The sensor's reading of the
    unfitted phase is ``c_alias = sum_m b_m phi_m``, ``b_m = D^H g_m / |D|² - a_m / A``, and its surface variance
    ``A sum_m |b_m|² Phi_m``. Frequencies where ``|D| <= cut max |D|`` (beyond a quarter of the band: the lowest
    orders are kept, as the finite reconstructor keeps them) give no reading. Both are integrated over the band.
    """
    d = pitch_m
    c = d / math.sqrt(2 * math.log(1 / coupling))
    w, t = edge_weights(m), np.linspace(-0.5, 0.5, m + 1)
    u = ((np.arange(n_k) + 0.5) / n_k - 0.5) / d
    fx, fy = np.meshgrid(u, u)
    lx, ly = (v.ravel() for v in np.meshgrid(np.arange(-n_aliases, n_aliases + 1), np.arange(-n_aliases, n_aliases + 1)))
    qx, qy = fx[..., None] + lx / d, fy[..., None] + ly / d
    psd = VON_KARMAN_COEFFICIENT * r0_m ** (-5 / 3) * (qx ** 2 + qy ** 2 + outer_scale_m ** -2) ** (-11 / 6)
    a = 2 * np.pi * c ** 2 * np.exp(-2 * np.pi ** 2 * c ** 2 * (qx ** 2 + qy ** 2)) / d ** 2

    def edge(q):
        return sum(wi * np.exp(2j * np.pi * q * ti * d) for wi, ti in zip(w, t, strict=True))

    sign = (-1.0) ** (lx + ly)
    gx, gy = 2j * np.sin(np.pi * qx * d) * edge(qy) * sign, 2j * np.sin(np.pi * qy * d) * edge(qx) * sign
    big_a = (a ** 2).sum(-1)
    dx, dy = (gx * a).sum(-1), (gy * a).sum(-1)
    d2 = np.abs(dx) ** 2 + np.abs(dy) ** 2
    b = (np.conj(dx)[..., None] * gx + np.conj(dy)[..., None] * gy) / d2[..., None] - a / big_a[..., None]
    kept = (np.sqrt(d2) > relative_cut * np.sqrt(d2.max())) | (np.hypot(fx, fy) * d < 0.25)
    area = (1 / (d * n_k)) ** 2
    aliasing = float((big_a * (np.abs(b) ** 2 * psd).sum(-1) * kept).sum() * area)
    fitting = float((psd - a ** 2 * psd / big_a[..., None]).sum(-1).sum() * area)
    return aliasing, fitting


@pytest.mark.physics
def test_four_samples_per_subaperture_measure_the_mean_gradient_two_alias_more():
    """The Fourier model's aliasing/fitting variance ratio against the edge rule: 0.60 with the 4 corners alone
    (``m = 1``), 0.236 with ``m = 2``, 0.189 with ``m = 4``, 0.179 for the exact mean gradient (``m = 16``). Four
    samples per side are within 6% of exact; two alias 32% more (for 4x fewer fine points)."""
    ratio = {m: np.divide(*fourier_aliasing(0.5, m, 0.1, n_k=32, n_aliases=6)) for m in (1, 2, 4, 16)}
    assert ratio[16] == pytest.approx(0.179, rel=0.03)
    assert ratio[4] / ratio[16] < 1.08 and 1.2 < ratio[2] / ratio[16] < 1.45 and ratio[1] > 3 * ratio[16]


@pytest.mark.physics
@pytest.mark.slow
def test_aliasing_of_exact_frozen_flow_matches_the_fourier_domain_spectrum():
    """Open loop, 16 across (Fried, ``m = 4``, 8 m, r0 0.1 m, L0 20 m): exact frozen-flow phase sampled by the
    ``point`` kernel on the sensor's fine grid, 64 independent frames. The DM-projected truth is the least-squares
    fit of the phase by the influence functions over the sensed area; the aliasing is the sensor's reading of the
    rest, ``IF R S (phi - IF y_fit)``. Fitting error against the Fourier model within 5% (21900 nm² against
    21700); aliasing/fitting variance away from the rim (3 pitches) 0.190 against 0.189 (within 20%). Over the
    whole sensed area it is 0.27: the least-squares reconstructor amplifies aliasing at the rim, as it does noise.
    Rigaut, Véran & Lai (1998) quote 0.35-0.4 for a DM with a sharp cut-off; a Gaussian DM fits worse (a larger
    denominator)."""
    grid = ActuatorGrid(8.0, 16)
    sensor = ShackHartmann().build(grid)
    geo = sensor.geometry
    atmosphere = Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=[Layer(1.0, 10.0, 0.0)],
                            kernel="point", screen_frames=16, remove_ptt=False)
    # 1 frame per second at 10 m/s: each frame is a new 8 m screen.
    phi = Turbulence(atmosphere, geo.fine_grid, 1.0, seed=5, stream="alias", n_realisations=4).frames(0, 16)
    phi = phi.reshape(-1, geo.n_fine).numpy()
    seen = geo.fine_in_subapertures
    y_fit = np.linalg.lstsq(sensor.influence[seen].toarray(), phi[:, seen].T, rcond=None)[0].T
    unfitted = phi - (sensor.influence @ y_fit.T).T
    alias = (sensor.influence @ sensor.sense(torch.as_tensor(unfitted)).numpy().T).T[:, seen]
    unfitted = unfitted[:, seen]

    def var(a):
        return float(((a - a.mean(1, keepdims=True)) ** 2).mean())

    inner = np.hypot(*geo.fine_positions_m[seen].T) < 4.0 - 3 * grid.pitch_m
    aliasing, fitting = fourier_aliasing(grid.pitch_m, 4, sensor.relative_cut)
    nm2 = (500 / (2 * np.pi)) ** 2
    assert var(unfitted) == pytest.approx(fitting * nm2, rel=0.05)
    assert var(alias[:, inner]) / var(unfitted[:, inner]) == pytest.approx(aliasing / fitting, rel=0.2)
    assert var(alias) / var(unfitted) > 1.2 * var(alias[:, inner]) / var(unfitted[:, inner])


# --- photon and read noise ----------------------------------------------------------------------------------------

def centroid_variance_px2(n_photons: float, fwhm_px: float, pixels: int, read_noise_e: float, draws: int,
                          rng: np.random.Generator) -> float:
    """Monte Carlo: x centre of gravity of a pixel-integrated Gaussian spot of ``fwhm_px`` on ``pixels x pixels``,
    Poisson photons and Gaussian read noise; the variance over ``draws`` frames (pixels²)."""
    sigma = fwhm_px / (2 * math.sqrt(2 * math.log(2)))
    edges = np.arange(pixels + 1) - pixels / 2
    line = np.diff(0.5 * (1 + erf(edges / (math.sqrt(2) * sigma))))
    spot = np.outer(line, line) / np.outer(line, line).sum()
    frames = rng.poisson(n_photons * spot, size=(draws, pixels, pixels)).astype(float)
    frames += read_noise_e * rng.standard_normal(frames.shape)
    x = np.arange(pixels) - (pixels - 1) / 2
    return float(((frames.sum(1) * x).sum(1) / frames.sum((1, 2))).var())


@pytest.mark.physics
def test_centroid_noise_matches_a_monte_carlo_of_the_detector():
    """Rousset's formulas (photon term for a Gaussian spot of FWHM ``N_T``) against centre-of-gravity centroids of a
    Gaussian spot (FWHM 2 pixels, Nyquist-sampled: ``N_D = 2``), 8 x 8 pixels, 0.5 e- read noise, for three
    magnitudes; in the slope unit (nm across the subaperture: ``x`` pixels are ``x lambda / N_D``). Within 25%
    (pixelisation adds ``1/12`` pixel² to the spot's variance, +12%)."""
    rng = np.random.default_rng(7)
    for magnitude in (7.0, 9.0, 11.0):
        det = Detector(band="R", magnitude=magnitude, throughput=0.5, pixels_across=8, pixels_per_lambda_over_d=2.0,
                       spot_fwhm_lambda_over_d=1.0, read_noise_e=0.5)
        n_ph = det.photons_per_subaperture(0.4, 1e-3)
        measured = centroid_variance_px2(n_ph, 2.0, 8, 0.5, 20000, rng) * (det.wavelength_m * 1e9 / 2.0) ** 2
        predicted = det.slope_noise_variance_nm2(0.4, 1e-3)
        assert measured == pytest.approx(predicted, rel=0.25), (magnitude, n_ph, measured, predicted)
    # Photons: OOPAO's zero point of R, 10^(-0.4 mag), throughput, area, frame period.
    assert Detector(magnitude=0.0, throughput=1.0).photons_per_subaperture(1.0, 1.0) == pytest.approx(4.01e12 / 368)
    assert PHOTOMETRY["H"][0] == 1.654e-6
    # Rousset's own photon coefficient is 0.69 (ln 2) of the Gaussian spot's.
    gauss, _ = Detector().phase_variance_rad2(100.0)
    rousset, _ = Detector(spot="rousset").phase_variance_rad2(100.0)
    assert rousset / gauss == pytest.approx(math.log(2))


# --- a pupil inside the actuator grid, partly lit subapertures ---------------------------------------------------

def oopao_like(n_sub: int = 20, pitch: float = 0.2) -> tuple[ActuatorGrid, ShackHartmann]:
    """OOPAO's Fried system of ``n_sub`` subapertures across: the pupil ``n_sub d`` inside ``n_sub + 1`` actuators,
    the actuators within ``D / 2 + 0.7533 d``, subapertures at least half lit."""
    grid = ActuatorGrid((n_sub + 1) * pitch, n_sub + 1, active_diameter_m=(n_sub + 2 * 0.7533) * pitch)
    return grid, ShackHartmann(pupil_diameter_m=n_sub * pitch, lit_fraction=0.5)


def test_partly_lit_subapertures_measure_their_lit_areas_mean_gradient():
    grid, config = oopao_like()
    sensor = config.build(grid)
    geo = sensor.geometry
    # OOPAO's counts at 20 across (tests/test_interop_oopao.py compares the sets themselves): 357 actuators, 316
    # subapertures; the 40 partly lit ones are between 59% and 97% lit.
    assert grid.n_actuators == 357 and geo.n_subapertures == 316
    partial = geo.illumination < 1
    assert partial.sum() == 40 and 0.5 <= geo.illumination.min() < 0.6
    x, y = geo.fine_positions_m.T
    n = geo.n_subapertures
    for a, b in ((1.0, 0.0), (0.0, 1.0), (0.3, -0.7)):  # a tilt: every slope exact, lit or not
        s = geo.slope_operator @ (a * x + b * y)
        np.testing.assert_allclose(s[:n], a * geo.pitch_m, atol=1e-12)
        np.testing.assert_allclose(s[n:], b * geo.pitch_m, atol=1e-12)
    # x² and y²: a partly lit subaperture's slopes are d times 2 <x> and 2 <y> over its lit area (sampled finely
    # here), not at its square's centre (what the fully lit rule gives).
    u = (np.arange(200) + 0.5) / 200 - 0.5
    errors, offsets = [], []
    for i in np.flatnonzero(partial):
        cx, cy = geo.centres_m[i]
        px, py = (g.ravel() for g in np.meshgrid(cx + u * geo.pitch_m, cy + u * geo.pitch_m))
        lit = np.hypot(px, py) <= geo.pupil_diameter_m / 2
        sx, sy = (geo.slope_operator @ x ** 2)[i], (geo.slope_operator @ y ** 2)[n + i]
        lit_x, lit_y = 2 * px[lit].mean() * geo.pitch_m, 2 * py[lit].mean() * geo.pitch_m
        errors += [abs(sx - lit_x), abs(sy - lit_y)]
        offsets += [abs(lit_x - 2 * cx * geo.pitch_m), abs(lit_y - 2 * cy * geo.pitch_m)]
    assert max(errors) < 0.1 * max(offsets)
    # The residual is scored over the lit pupil only, and a partly lit subaperture's slopes are 1 / lit noisier.
    assert np.hypot(x, y)[geo.fine_in_pupil].max() <= geo.pupil_diameter_m / 2 + 1e-12
    np.testing.assert_allclose(sensor.slope_noise_scale, np.tile(geo.illumination, 2) ** -0.5)
    assert sensor.noise_propagation() > float((sensor.reconstructor ** 2).sum() / grid.n_actuators)


def test_without_the_new_options_the_sensor_is_unchanged():
    grid = ActuatorGrid(4.0, 10)
    base, explicit = ShackHartmann().build(grid), ShackHartmann(pupil_diameter_m=4.0).build(grid)
    assert (base.geometry.slope_operator != explicit.geometry.slope_operator).nnz == 0
    assert (base.slope_noise_scale == 1).all() and ActuatorGrid(4.0, 10, active_diameter_m=4.0) .n_actuators == 80


# --- bad input ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("build, match", [
    (lambda: Detector(magnitude=float("nan")), r"^magnitude=nan is invalid: it must be a finite number$"),
    (lambda: Detector(pixels_across=0), r"^pixels_across=0 is invalid: it must be an integer >= 1$"),
    (lambda: Detector(pixels_per_lambda_over_d=0.0), r"^pixels_per_lambda_over_d=0.0 is invalid"),
    (lambda: Detector(throughput=1.5), r"^throughput=1.5 is invalid: it must be a finite number in \(0, 1\]"),
    (lambda: Detector(throughput=0.0), r"^throughput=0.0 is invalid"),
    (lambda: Detector(band="Q"), r"^band='Q' is invalid: it must be one of U, B"),
    (lambda: ShackHartmann(geometry="cell", subapertures_across=12).build(ActuatorGrid(4.0, 10)),
     r"^subapertures_across=12 is invalid: it must be an integer in \[2, 10\] \(subapertures across; the grid has "
     r"10 actuators across\)$"),
    (lambda: ShackHartmann(geometry="pyramid"), r"^geometry='pyramid' is invalid: it must be one of fried, cell$"),
    (lambda: ShackHartmann(mechanical_coupling=1.0), r"^mechanical_coupling=1.0 is invalid"),
    (lambda: ShackHartmann(geometry="cell", samples_per_subaperture=16).build(ActuatorGrid(8.0, 40)),
     r"^samples_per_subaperture=16 with 40 subapertures across needs a fine grid of \d+ points across: allowed at "
     r"most 512"),
    (lambda: ShackHartmann(geometry="fried", subapertures_across=10).build(ActuatorGrid(4.0, 10)),
     r"^subapertures_across=10 is invalid for geometry 'fried' on 10 actuators across: it has 9"),
    (lambda: ShackHartmann(pupil_diameter_m=4.5).build(ActuatorGrid(4.0, 10)),
     r"^sensor.pupil_diameter_m=4.5 is invalid: it must be a finite number in \(0, 4\] \(m \(the actuator grid is 4 m "),
    (lambda: ShackHartmann(lit_fraction=0.0), r"^lit_fraction=0.0 is invalid: it must be null or a finite number in \(0, 1\]"),
    (lambda: ActuatorGrid(4.0, 10, active_diameter_m=6.0), r"^active_diameter_m=6.0 is invalid: it must be a finite "
     r"number in \(0, 5.65"),
])
def test_bad_input_is_one_line(build, match):
    with pytest.raises(ConfigError, match=match) as err:
        build()
    assert "\n" not in str(err.value)


def test_shapes_that_do_not_fit_are_one_line(sensor10):
    s = sensor10
    with pytest.raises(ConfigError, match=r"^reconstructor of shape \(80, 10\) does not fit: expected \(80, 122\)"):
        s.reconstruct(torch.zeros(s.n_slopes), reconstructor=np.zeros((80, 10)))
    with pytest.raises(ConfigError, match=r"^slopes of shape \(3, 7\) does not fit: its last dimension must be 122"):
        s.reconstruct(torch.zeros(3, 7))
    with pytest.raises(ConfigError, match=r"^phase_fine of shape \(5,\) does not fit"):
        s.slopes(torch.zeros(5))
    with pytest.raises(ConfigError, match=r"^n_photons=0.0 is invalid"):
        Detector().phase_variance_rad2(0.0)
