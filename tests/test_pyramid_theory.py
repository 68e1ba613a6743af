"""The modulated pyramid (:mod:`eofnn.sim.sensing.pyramid_optics`) against the published theory, each within 20%:

- **linearity range against modulation**: a tip of ``a lambda / D`` read through its own interaction vector (a
  one-mode reconstructor) is linear up to about the modulation radius ``r`` and saturates there: for the geometric
  modulated pyramid the slope signal is ``(2 / pi) arcsin(a / r)`` up to ``a = r``, then flat (Vérinaud 2004, Opt.
  Commun. 233, 27), so the estimate ``r arcsin(a / r)`` peaks at ``a = r``, its small-signal gain falls as ``1 / r``;
- **photon-noise propagation per Fourier mode**: the variance of a mode's least-squares estimate from Poisson-noisy
  frames is ``1 / sensitivity²``; modulated by ``r``, the sensitivity to spatial frequency ``f < r`` (cycles per
  pupil) is ``(2 / pi) f / r`` of the fixed pyramid's, the fixed one's about flat in ``f`` (Vérinaud 2004). The
  propagation is measured by Monte Carlo here, not from the sensitivity's formula (``tests/test_pyramid.py`` checks
  that one). Above ``r`` Guyon 2005 (ApJ 629, 592) gives the modulated pyramid twice the fixed one's noise (beta =
  sqrt(2) against 1): the least-squares estimate from slopes maps does not reach it (1.0 to 1.1 times, up to f =
  3.5 r: slopes maps lose more of the fixed pyramid's information than of the modulated one's), so only a loose bound
  is asserted there;
- **photon-noise-limited sensitivity** (Guyon's own measure): the Fisher information per photon of the detector's
  pixels, ``sum_k (dI_k / da)² / I_k``, the inverse of the smallest variance any estimate from the frames can reach:
  above ``r`` the modulated pyramid's is half the fixed one's (Guyon 2005), below ``r`` its square root is
  ``(2 / pi) f / r`` of the fixed one's (Vérinaud 2004).

Tiny pupils: 16 pixels across, 2 points per pixel, I band.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.sensing.detector import PHOTOMETRY
from eofnn.sim.sensing.pyramid import PyramidOptics, PyramidSignals

PIXELS, SAMPLES = 16, 2
WAVELENGTH_NM = PHOTOMETRY["I"][0] * 1e9
PUPIL = ActuatorGrid(8.0, PIXELS * SAMPLES)
X, Y = PUPIL.positions_m.T / 8.0  # pupil coordinates in diameters


def _pyramid(modulation: float) -> tuple[PyramidOptics, PyramidSignals]:
    optics = PyramidOptics(PUPIL.mask, PIXELS, SAMPLES, 2, modulation, None, WAVELENGTH_NM)
    return optics, PyramidSignals(optics, "slopes_maps")


def _interaction(optics: PyramidOptics, signals: PyramidSignals, shape_nm: np.ndarray, eps: float = 1e-2):
    """Push-pull response ``(n_signals,)`` per unit of ``shape_nm`` (nm per unit) about a flat wavefront."""
    opd = torch.as_tensor(np.stack([shape_nm, -shape_nm]) * eps)
    plus, minus = signals.process(optics.frames(opd))
    return (plus - minus) / (2 * eps)


@pytest.fixture(scope="module")
def tip_curves() -> dict[float, tuple[np.ndarray, np.ndarray, float]]:
    """Per modulation radius ``r`` (lambda / D): tip amplitudes (lambda / D), their one-mode estimates, and the
    small-signal response's norm."""
    out = {}
    tip = WAVELENGTH_NM * X  # 1 lambda / D of tip: one wave of OPD across the pupil
    for r in (2.0, 4.0, 6.0):
        optics, signals = _pyramid(r)
        d = _interaction(optics, signals, tip)
        amplitudes = np.linspace(0.25, 2.0 * r, 24)
        s = signals.process(optics.frames(torch.as_tensor(amplitudes[:, None] * tip[None])))
        out[r] = (amplitudes, (s @ d / (d @ d)).numpy(), float(d.norm()))
    return out


@pytest.mark.physics
def test_the_tip_is_read_linearly_up_to_about_the_modulation_radius_and_saturates_there(tip_curves):
    """The saturation point, where the estimate reaches 90% of its plateau (the geometric model's ``r sin(0.45 pi)``
    = 0.988 r), is at ``r`` within 20% and scales with ``r`` (2, 4, 6 lambda / D) within 20% (measured 1.08 r, 1.01 r,
    0.98 r); below ``r / 2`` the estimate is within 15% of the tip (``r arcsin(1/2) / (r/2)`` = 1.05); at ``2 r`` it
    is at most ``r (pi / 2) / 2 r`` = 0.79 of it (+20%)."""
    peaks = {}
    for r, (a, estimate, _) in tip_curves.items():
        top = int(np.argmax(estimate))
        peaks[r] = np.interp(0.9 * estimate[top], estimate[:top + 1], a[:top + 1])
        assert peaks[r] / r == pytest.approx(math.sin(0.45 * math.pi), rel=0.2)
        linear = a <= r / 2
        assert np.all(np.abs(estimate[linear] / a[linear] - 1) < 0.15)
        assert estimate[-1] / a[-1] < 1.2 * math.pi / 4
    assert peaks[4.0] / peaks[2.0] == pytest.approx(2.0, rel=0.2)
    assert peaks[6.0] / peaks[2.0] == pytest.approx(3.0, rel=0.2)


@pytest.mark.physics
def test_the_small_signal_tip_response_falls_as_one_over_the_modulation_radius(tip_curves):
    """The slope signal's gain is ``2 / (pi r)`` per lambda / D: the response's norm at 4 and 6 lambda / D is 1/2 and
    1/3 of that at 2 lambda / D within 20% (measured 0.48, 0.32)."""
    norm = {r: curve[2] for r, curve in tip_curves.items()}
    assert norm[4.0] / norm[2.0] == pytest.approx(0.5, rel=0.2)
    assert norm[6.0] / norm[2.0] == pytest.approx(1 / 3, rel=0.2)


def _noise_propagation(r: float, frequencies: np.ndarray, draws: int, photons: float, seed: int) -> np.ndarray:
    """Variance (rad², times the photons) of each Fourier mode's least-squares estimate ``d^T s / d^T d`` from
    ``draws`` Poisson-noisy frames of a flat wavefront, ``photons`` per frame."""
    optics, signals = _pyramid(r)
    to_nm = WAVELENGTH_NM / (2 * math.pi)
    d = torch.stack([_interaction(optics, signals, to_nm * np.cos(2 * np.pi * f * X)) for f in frequencies])
    flat = optics.frames(torch.zeros(optics.n_pupil)).expand(draws, -1, -1)
    noisy = torch.poisson(flat * photons, generator=torch.Generator().manual_seed(seed))
    s = signals.process(noisy)
    estimates = (s - s.mean(0)) @ d.T / (d * d).sum(-1)
    return estimates.var(0).numpy() * photons


@pytest.mark.physics
def test_photon_noise_propagation_per_fourier_mode_follows_the_modulated_sensitivity():
    """Noise propagation ``1 / sensitivity²``, measured (Poisson frames, the slopes' covariance as it comes).
    Modulated by ``r = 4``, below ``r`` the sensitivity is ``(2 / pi) f / r`` of the fixed pyramid's within 20%
    (measured 1.19, 1.09, 1.14 times it at f = 1, 2, 3: diffraction helps at the lowest frequencies), so ``f² var``
    is flat there (slopes: measured within 11%); at ``f = 1`` it propagates ``(4 / 2)²`` = 4 times the noise of
    ``r = 2`` within 20% (measured 4.4); the fixed pyramid's sensitivity is flat within 20% (f = 1 to 5). Above
    ``r`` the modulated one leaves the slopes' regime: between 0.8 and 2.4 times the fixed one's noise (Guyon's ideal
    is 2; measured 1.1 at f = 5, 6: module docstring)."""
    frequencies = np.array([1.0, 2.0, 3.0, 5.0, 6.0])
    draws, photons = 3000, 1e6
    fixed = _noise_propagation(0.0, frequencies, draws, photons, 1)
    mod4 = _noise_propagation(4.0, frequencies, draws, photons, 2)
    mod2 = _noise_propagation(2.0, frequencies[:1], draws, photons, 3)
    assert math.sqrt(fixed[:4].max() / fixed[:4].min()) < 1.2
    below = frequencies < 4.0
    sensitivity_ratio = np.sqrt(fixed[below] / mod4[below])
    assert sensitivity_ratio / (2 / math.pi * frequencies[below] / 4.0) == pytest.approx(1.0, rel=0.2)
    slopes = mod4[below] * frequencies[below] ** 2
    assert slopes.max() / slopes.min() < 1.2
    assert mod4[0] / mod2[0] == pytest.approx(4.0, rel=0.2)
    assert np.all((mod4[~below] / fixed[~below] > 0.8) & (mod4[~below] / fixed[~below] < 2.4))


def _fisher(r: float, frequencies: np.ndarray) -> np.ndarray:
    """Fisher information per photon (rad⁻²) of each Fourier mode in the detector's pixels about a flat wavefront:
    ``sum_k (dI_k / da)² / I_k`` (``I_k`` the pixel's fraction of the photons)."""
    optics, _ = _pyramid(r)
    to_nm = WAVELENGTH_NM / (2 * math.pi)
    flat = optics.frames(torch.zeros(optics.n_pupil))
    lit = flat > 1e-12
    out = []
    for f in frequencies:
        shape = to_nm * np.cos(2 * np.pi * f * X)
        eps = 1e-2
        plus, minus = optics.frames(torch.as_tensor(np.stack([shape, -shape]) * eps))
        derivative = (plus - minus) / (2 * eps)
        out.append(float((derivative[lit] ** 2 / flat[lit]).sum()))
    return np.array(out)


@pytest.mark.physics
def test_the_photon_noise_limited_sensitivity_follows_guyon_above_and_verinaud_below_the_radius():
    """Fisher information of the pixels (module docstring): above the radius (r = 2, f = 3 to 6) the modulated
    pyramid needs twice the fixed one's photons for the same noise within 20% (measured 1.89-1.91, Guyon's beta =
    sqrt(2)); below it (r = 2, 3; f < r) its sensitivity is ``(2 / pi) f / r`` of the fixed one's within 20% (measured
    0.95 at r = 2, 0.89 and 0.86 at r = 3); the fixed pyramid's sensitivity is flat within 20% (f = 1 to 6)."""
    frequencies = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    fixed = _fisher(0.0, frequencies)
    assert math.sqrt(fixed.max() / fixed.min()) < 1.2
    mod2 = _fisher(2.0, frequencies)
    above = frequencies > 2.0
    assert fixed[above] / mod2[above] == pytest.approx(2.0, rel=0.2)
    mod3 = _fisher(3.0, frequencies[:2])
    for r, fisher in ((2.0, mod2[:1]), (3.0, mod3)):
        f = frequencies[:len(fisher)]
        ratio = np.sqrt(fisher / fixed[:len(fisher)])
        assert ratio / (2 / math.pi * f / r) == pytest.approx(1.0, rel=0.2)
