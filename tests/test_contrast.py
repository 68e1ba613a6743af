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


def test_the_spatial_split_sums_to_the_pupil_variance_and_puts_each_ripple_in_its_region():
    """Parseval: the three regions' variances sum to the piston-removed variance over the pupil. A ripple of 6
    cycles per pupil lies inside the control circle (20 lambda/D here); a diagonal one of 17 + 17 cycles (24 lambda/D
    from the axis, inside the square) in its corners; on a finer grid whose control radius is 10 lambda/D, one of 30
    cycles beyond the square."""
    gen = torch.Generator().manual_seed(1)
    eps = 20.0 * torch.randn(1, 5, GRID.n_actuators, dtype=torch.float64, generator=gen)
    contrast = RawContrast(GRID, WAVELENGTH_M, every=1)
    contrast(0, {"eps": eps})
    split = contrast.spatial_split()
    variance = (eps[0] - eps[0].mean(-1, keepdim=True)).pow(2).mean(-1).mean()
    assert sum(v * v for v in split.values()) == pytest.approx(float(variance), rel=1e-9)
    assert split["beyond_control"] == pytest.approx(0.0, abs=1e-9)  # the actuator grid reaches the square only

    def shares(grid, ripple, **kw):
        c = RawContrast(grid, WAVELENGTH_M, every=1, **kw)
        if "pupil" in kw:
            c.add(ripple[kw["pupil"]].view(1, -1).to(torch.float64))
        else:
            c(0, {"eps": ripple.view(1, 1, -1).to(torch.float64)})
        parts = {k: v * v for k, v in c.spatial_split().items()}
        return {k: v / sum(parts.values()) for k, v in parts.items()}

    x, y = (torch.as_tensor(GRID.positions_m[:, i]) for i in (0, 1))
    assert shares(GRID, torch.cos(2 * math.pi * 6 * x / 8.0))["inside_control_circle"] > 0.9
    assert shares(GRID, torch.cos(2 * math.pi * 17 * (x + y) / 8.0))["control_square_corners"] > 0.8
    fine = ActuatorGrid(8.0, 80)
    fx = torch.as_tensor(fine.positions_m[:, 0])
    pupil = torch.as_tensor(fine.positions_m).norm(dim=1).numpy() <= 4.0
    assert shares(fine, torch.cos(2 * math.pi * 30 * fx / 8.0), pupil=pupil, pupil_diameter_m=8.0,
                  control_radius_lod=10.0)["beyond_control"] > 0.9


def test_the_halo_is_the_residual_variance_at_its_separations():
    """To first order in the phase, white residuals give a flat contrast ``sigma_phi² / N`` per focal-plane pixel
    (``1 / padding`` lambda/D on a side), so the halo times ``2 pi dr`` (rings ``dr`` apart) is the variance
    ``sigma_phi² pi (R² - r0²) / N`` of the spatial frequencies between ``r0`` and the reach ``R`` (the pupil's
    ``N`` points fill ``N`` (lambda/D)² of frequencies); twice the residual gives four times the halo."""
    from eofnn.evaluation.contrast import HALO_FROM_LOD, halo

    grid = ActuatorGrid(4.0, 16)
    gen = torch.Generator().manual_seed(2)
    eps = torch.randn(1, 300, grid.n_actuators, dtype=torch.float64, generator=gen)
    found = {}
    for sigma_nm in (5.0, 10.0):
        contrast = RawContrast(grid, WAVELENGTH_M, every=1)
        contrast(0, {"eps": sigma_nm * eps})
        found[sigma_nm] = halo(*contrast.profile())
    value, reach = found[5.0]
    dr = 1 / 4  # RawContrast's default padding: 4 pixels per lambda/D
    assert reach == pytest.approx(grid.n_across / 2 - dr)  # the last bin inside the control radius
    phase_var = (2 * math.pi * 5.0e-9 / WAVELENGTH_M) ** 2
    expected = phase_var * math.pi * ((reach + dr / 2) ** 2 - (HALO_FROM_LOD - dr / 2) ** 2) / grid.n_actuators
    assert 2 * math.pi * dr * value == pytest.approx(expected, rel=0.1)
    assert found[10.0][0] / value == pytest.approx(4.0, rel=1e-3)
    assert halo([0.0, 0.25], [1.0, 1.0]) is None  # nothing from 0.5 lambda/D on
    assert halo([0.5, 1.0, 1.5], [1e-3, None, 2e-3]) == pytest.approx((0.5e-3 + 3e-3, 1.5))
