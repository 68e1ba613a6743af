"""What a loop keeps of white measurement noise (eofnn/analysis/noise.py), and the best a predictor could do against
a controller's error budget (eofnn/evaluation/budget.py: temporal_bound), against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eofnn.analysis.noise import integrator_noise_gain
from eofnn.errors import ConfigError
from eofnn.evaluation.budget import temporal_bound

pytestmark = pytest.mark.physics


@pytest.mark.parametrize("k", [0.1, 0.5, 1.0, 1.5, 1.9])
def test_one_frame_of_delay_keeps_k_over_2_minus_k(k):
    """``d = 1``: ``h(n) = -k (1 - k)^(n-1)``, so ``sum h² = k² / (1 - (1 - k)²) = k / (2 - k)``."""
    assert integrator_noise_gain(k, delay_frames=1) == pytest.approx(k / (2 - k), rel=1e-9)


@pytest.mark.parametrize("k", [0.1, 0.37, 0.56, 0.9])
def test_two_frames_of_delay_keep_the_variance_of_an_ar2_process(k):
    """``d = 2``: ``1 / (1 - z^-1 + k z^-2)`` is an AR(2) process of unit innovations, of variance
    ``(1 + a2) / ((1 - a2) ((1 + a2)² - a1²))`` with ``a1 = -1``, ``a2 = k``; times ``k²``."""
    assert integrator_noise_gain(k) == pytest.approx(k * (1 + k) / ((1 - k) * (2 + k)), rel=1e-9)


def test_the_noise_gain_is_what_a_simulated_loop_keeps():
    """A two-frame loop driven by white noise alone: the command's variance over the noise's is the noise gain."""
    k, frames = 0.5, 200_000
    noise = np.random.default_rng(0).standard_normal(frames)
    y = np.zeros(frames)
    for n in range(2, frames):
        y[n] = y[n - 1] - k * (y[n - 2] + noise[n - 2])  # m(n-2) = eps + w, with no turbulence eps = y
    assert y[1000:].var() / noise.var() == pytest.approx(integrator_noise_gain(k), rel=0.03)


def test_an_unstable_loop_keeps_all_of_it_and_bad_input_is_refused():
    assert integrator_noise_gain(1.0) == math.inf  # d = 2: the limit is k = 1
    assert integrator_noise_gain(2.5, delay_frames=1) == math.inf
    with pytest.raises(ConfigError, match="loop_gain must be positive"):
        integrator_noise_gain(-0.1)
    with pytest.raises(ConfigError, match="delay_frames must be a whole number"):
        integrator_noise_gain(0.5, delay_frames=1.5)


def test_the_temporal_bound_removes_the_temporal_term_alone():
    """With the budget's terms in quadrature, removing the temporal term leaves aliasing and noise: the bound is
    ``1 + temporal² / (aliasing² + noise²)``; with neither left, a perfect predictor removes everything."""
    fitting, aliasing, noise, temporal = 40.0, 30.0, 20.0, 50.0
    total = math.sqrt(fitting ** 2 + aliasing ** 2 + noise ** 2 + temporal ** 2)
    budget = {"fitting_nm": fitting, "aliasing_nm": aliasing, "noise_nm": noise, "temporal_nm": temporal}
    assert temporal_bound(total, budget) == pytest.approx(1 + temporal ** 2 / (aliasing ** 2 + noise ** 2))
    assert temporal_bound(total, {"fitting_nm": fitting, "aliasing_nm": None, "noise_nm": noise}) == pytest.approx(
        (aliasing ** 2 + noise ** 2 + temporal ** 2) / noise ** 2)
    assert temporal_bound(total, {"fitting_nm": fitting}) == math.inf
    assert temporal_bound(total, None) == math.inf
    assert temporal_bound(10.0, {"fitting_nm": 20.0, "noise_nm": 5.0}) == 0.0  # fitting above the median: nothing left
