"""The von Karman structure function the Shack-Hartmann diagnostics compare eofnn's and OOPAO's turbulence with:
its two textbook limits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eofnn.studies.sh_diagnostics import von_karman_structure_function

NM2_PER_RAD2 = (500e-9 * 1e9 / (2 * math.pi)) ** 2  # r0 given at 500 nm


def test_far_below_the_outer_scale_it_is_kolmogorovs():
    """D(r) -> 6.88 (r / r0)^(5/3) rad², less the outer scale's first correction, 1.485 (r / L0)^(1/3)."""
    r, r0, outer = 0.01, 0.1, 1e4
    got = float(von_karman_structure_function(np.array([r]), r0, outer)[0]) / NM2_PER_RAD2
    kolmogorov = 6.8839 * (r / r0) ** (5 / 3)
    assert got == pytest.approx(kolmogorov * (1 - 1.485 * (r / outer) ** (1 / 3)), rel=2e-3)


def test_far_beyond_the_outer_scale_it_is_twice_the_phase_variance():
    """D(r >> L0) -> 2 sigma², sigma² = 0.0863 (L0 / r0)^(5/3) rad² (Conan 2000)."""
    r0, outer = 0.15, 20.0
    got = float(von_karman_structure_function(np.array([1e5]), r0, outer)[0]) / NM2_PER_RAD2
    assert got == pytest.approx(2 * 0.0863 * (outer / r0) ** (5 / 3), rel=2e-3)
