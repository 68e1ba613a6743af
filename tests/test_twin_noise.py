"""The twin's WFS-noise estimate (``eofnn.training.twin_seeing``): the white floor of the POL values' temporal
cross-periodogram above fs/4 beside an ``f^(-11/3)`` turbulence tail, less the share of the twin's own turbulence
floor that the record shows."""

from __future__ import annotations

import numpy as np

from eofnn.training.twin_seeing import R0_REFERENCE_M, mean_spectrum, noise_covariance, noise_floor, seeing_and_noise


def _shaped(rng, frames: int, k: int, gain) -> np.ndarray:
    """``(frames, K)`` independent series whose periodogram level is ``gain(f)²`` (white of variance 1 filtered)."""
    f = np.fft.rfftfreq(frames)
    return np.fft.irfft(np.fft.rfft(rng.normal(size=(frames, k)), axis=0) * gain(f)[:, None], n=frames, axis=0)


def _tail(level: float):
    """An ``f^(-11/3)`` spectrum (flattened below 0.01 cycles per frame) of ``level`` at fs/4."""
    return lambda f: np.sqrt(level) * (np.maximum(f, 0.01) / 0.25) ** (-11 / 6)


def test_the_spectral_floor_recovers_coloured_white_noise_under_an_f_minus_11_3_tail_where_the_lag_estimate_fails():
    """Turbulence as strong as the noise at fs/4 and falling as f^(-11/3): the floor is the noise's covariance,
    spatial colour included, within a few %, where ``(4 D(1) - D(2)) / 6`` is 44% high (the tail is not smooth over
    two frames)."""
    rng = np.random.default_rng(3)
    frames, k = 16000, 6
    mixing = np.eye(k) + 0.5 * np.eye(k, k=1)  # neighbours' noise correlated
    noise = rng.normal(size=(frames, k)) @ mixing.T * 10.0
    truth = 100.0 * mixing @ mixing.T
    pol = noise + _shaped(rng, frames, k, _tail(100.0))
    found, old = noise_floor(pol), noise_covariance(pol)
    assert abs(np.diag(found).mean() / np.diag(truth).mean() - 1) < 0.03
    assert np.abs(found - truth).max() < 0.1 * truth.max()
    assert np.diag(old).mean() / np.diag(truth).mean() - 1 > 0.3


def test_the_twins_high_frequency_floor_is_removed_in_the_share_the_record_shows():
    """The twin's noise-free turbulence has an aliased sensor's high-frequency excess beside a weak f^(-11/3) tail:
    a bump at 0.19-0.25 cycles per frame (20 times the noise's level) and a floor of twice above. A record with the
    same excess gets all of its floor removed, one without (another simulator's smoother turbulence) none of it:
    both give the noise within 5%, where removing the whole floor from the second would leave less than nothing and
    removing none from the first three times the noise's variance."""
    rng = np.random.default_rng(5)
    frames, k, sigma2 = 16000, 36, 100.0
    positions = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0)), -1).reshape(-1, 2) * 0.5
    tail = _tail(0.02 * sigma2)
    floor = lambda f: np.sqrt(sigma2 * np.where(f >= 0.25, 2.0, np.where(f > 0.18, 20.0, 0.0)))  # noqa: E731
    both = lambda f: np.sqrt(tail(f) ** 2 + floor(f) ** 2)  # noqa: E731
    reference = [_shaped(rng, frames, k, both) for _ in range(2)]
    refs = {l0: (sum(np.cov(r.T) for r in reference) / 2, sum(noise_floor(r) for r in reference) / 2, positions,
                 sum(mean_spectrum(r) for r in reference) / 2) for l0 in (10.0, 20.0)}
    noise = rng.normal(size=(frames, k)) * np.sqrt(sigma2)
    for shape, share in ((both, 1.0), (tail, 0.0)):
        pol = noise + _shaped(rng, frames, k, shape)
        cv, seeing = seeing_and_noise(pol, refs, positions, 0.5)
        assert abs(np.diag(cv).mean() / sigma2 - 1) < 0.05, (share, np.diag(cv).mean())
        assert abs(seeing["aliasing_share"] - share) < 0.15
        assert seeing["r0_m"] < 2 * R0_REFERENCE_M
    assert np.diag(noise_floor(noise + _shaped(rng, frames, k, both))).mean() > 2 * sigma2
