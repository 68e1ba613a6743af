"""Raw contrast behind a perfect coronagraph against theory: nothing left for a flat wavefront, a flat halo of
sigma_phi^2 / N_actuators for white residuals, and a speckle at k lambda/D for a ripple of k cycles per pupil."""

from __future__ import annotations

import math

import pytest
import torch

from eofnn.evaluation.contrast import RawContrast
from eofnn.sim.grid import ActuatorGrid

pytestmark = pytest.mark.physics

GRID = ActuatorGrid(8.0, 40)
WAVELENGTH_M = 1.65e-6


def test_a_flat_wavefront_leaves_no_light():
    contrast = RawContrast(GRID, WAVELENGTH_M)
    contrast(0, {"eps": torch.full((1, 30, GRID.n_actuators), 123.0, dtype=torch.float64)})  # piston only
    assert all(v == pytest.approx(0.0, abs=1e-20) for v in contrast.at().values())


@pytest.mark.slow
def test_white_residuals_give_the_flat_halo_of_theory():
    sigma_nm = 20.0
    contrast = RawContrast(GRID, WAVELENGTH_M, every=1)
    gen = torch.Generator().manual_seed(0)
    contrast(0, {"eps": sigma_nm * torch.randn(1, 400, GRID.n_actuators, dtype=torch.float64, generator=gen)})
    phase_var = (2 * math.pi * sigma_nm * 1e-9 / WAVELENGTH_M) ** 2
    expected = (1 - math.exp(-phase_var)) / GRID.n_actuators
    for value in contrast.at().values():
        assert value == pytest.approx(expected, rel=0.1)


def test_a_ripple_of_k_cycles_puts_a_speckle_at_k_lambda_over_d():
    k = 6
    x = torch.as_tensor(GRID.positions_m[:, 0])
    eps = 10.0 * torch.cos(2 * math.pi * k * x / GRID.diameter_m)
    contrast = RawContrast(GRID, WAVELENGTH_M, every=1)
    contrast(0, {"eps": eps.view(1, 1, -1).to(torch.float64)})
    separations, profile = contrast.profile()
    peak = separations[max(range(2, len(profile)), key=profile.__getitem__)]
    assert peak == pytest.approx(k, abs=0.5)
    assert contrast.at((2.0, 50.0))["50"] is None  # beyond the control radius of 20 lambda/D
