"""The flagship Shack-Hartmann job (configs/flagship_sh.yaml) and what makes it affordable: non-lattice screens built
side by side to the same numbers, their accumulation by runs of rows equal to ``index_add_``, and two fine samples
per subaperture side keeping the error budget's fitting and aliasing terms of four within 10%."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Turbulence
from eofnn.sim.atmosphere import anywind
from eofnn.sim.atmosphere.exact import lattice_direction
from eofnn.sim.loop.sensing import loop_operators
from eofnn.sim.scenario import Scenario

ROOT = Path(__file__).resolve().parents[1]
FLAGSHIP = ROOT / "configs" / "flagship_sh.yaml"
TINY = Path(__file__).parent / "conf" / "flagship_tiny.yaml"


def _sky(n_across: int, samples: int, frames: int) -> Scenario:
    """The flagship's sky and sensor (r0 15 cm at 500 nm, L0 20 m, 10 m/s at 30 deg and 20 m/s at 120 deg, 1 kHz,
    delay 2, Fried geometry, no detector) on ``n_across`` actuators at its 0.2 m pitch."""
    return Scenario.from_dict({
        "grid": {"diameter_m": 0.2 * n_across, "n_across": n_across},
        "atmosphere": {"r0_m": 0.15, "r0_wavelength_m": 5e-7, "outer_scale_m": 20.0, "screen_frames": frames,
                       "layers": [{"cn2_fraction": 0.6, "wind_speed_mps": 10.0, "wind_direction_deg": 30.0},
                                  {"cn2_fraction": 0.4, "wind_speed_mps": 20.0, "wind_direction_deg": 120.0}]},
        "plant": {"delay_frames": 2}, "sensor": {"kind": "shack_hartmann", "samples_per_subaperture": samples}})


def test_the_flagship_is_extreme_ao_through_a_shack_hartmann_with_winds_off_the_lattice():
    """What the README promises of its first command: 8 m, 40 x 40, r0 at least 12 cm at 500 nm, an R or I = 8 guide
    star, 1-2 kHz, two layers whose directions are not lattice directions of the grid."""
    config = yaml.safe_load(FLAGSHIP.read_text())
    scenario = Scenario.from_dict(config["scenario"])
    atm = scenario.atmosphere
    assert scenario.grid.diameter_m == 8.0 and scenario.grid.n_across == 40
    assert scenario.sensor.is_shack_hartmann
    assert atm.r0_m * (5e-7 / atm.r0_wavelength_m) ** 1.2 >= 0.12  # r0 grows as the wavelength to the 6/5
    assert scenario.sensor.detector.band in ("R", "I") and scenario.sensor.detector.magnitude == 8.0
    assert 1000 <= scenario.frame_rate_hz <= 2000
    assert len(atm.layers) == 2
    assert all(lattice_direction(lay.wind_direction_deg) is None for lay in atm.layers)
    names = set(config["predictors"])
    assert {"integrator", "lqg"} <= names
    assert any(p.get("fallback") for p in config["predictors"].values())
    assert any(p.get("data", {}).get("target") == "dm_fit" for p in config["predictors"].values())


def test_the_tiny_flagship_is_the_flagship_with_smaller_numbers():
    """tests/conf/flagship_tiny.yaml: the flagship's contenders and sky, only sizes changed."""
    big, tiny = yaml.safe_load(FLAGSHIP.read_text()), yaml.safe_load(TINY.read_text())
    assert set(big["predictors"]) == set(tiny["predictors"])
    for key in ("r0_m", "r0_wavelength_m", "outer_scale_m", "layers"):
        assert big["scenario"]["atmosphere"][key] == tiny["scenario"]["atmosphere"][key]
    assert big["scenario"]["sensor"] == tiny["scenario"]["sensor"]


def test_runs_of_rows_add_as_index_add_does():
    """The synthesis adds rows by runs of consecutive targets: the same sums, in the same order, as ``index_add_``,
    with targets that wrap, go down, repeat and skip."""
    rng = np.random.default_rng(0)
    m_period, half = 11, 6
    for q0, rows in ((0, 40), (7, 5), (3, 23)):
        q = np.arange(q0, q0 + rows)
        source = torch.as_tensor(rng.standard_normal((rows, 3)) + 1j * rng.standard_normal((rows, 3))).to(
            torch.complex64)
        m, mirror = q % m_period, (-q % m_period)
        expected = torch.zeros(half, 3, dtype=torch.complex64)
        low, high = torch.as_tensor(m < half), torch.as_tensor(mirror < half)
        expected.index_add_(0, torch.as_tensor(m)[low], torch.conj_physical(source[low]))
        expected.index_add_(0, torch.as_tensor(mirror)[high], source[high])
        got = torch.zeros(half, 3, dtype=torch.complex64)
        for rows_at, targets, conjugate in ((m < half, m, True), (mirror < half, mirror, False)):
            for (a, b), (lo, hi), step in anywind._runs(np.flatnonzero(rows_at), targets):
                part = source[a:b] if step > 0 else source[a:b].flip(0)
                got[lo:hi].add_(part.conj() if conjugate else part)
        assert torch.equal(got, expected)


def test_screens_built_side_by_side_are_the_numbers_built_one_after_the_other(monkeypatch):
    """Two realisations of two non-lattice layers: built in threads or one by one, the frames are bit for bit equal."""
    atmosphere = Atmosphere(model="exact", screen_frames=300, layers=[Layer(0.6, 10.0, 30.0), Layer(0.4, 20.0, 120.0)])
    grid = ActuatorGrid(1.6, 8)
    anywind._SCREEN_CACHE.clear()
    side_by_side = Turbulence(atmosphere, grid, 1000.0, 3, "test", 2).frames(0, 300)
    anywind._SCREEN_CACHE.clear()
    monkeypatch.setattr(anywind, "_MAX_BUILD_THREADS", 1)
    one_by_one = Turbulence(atmosphere, grid, 1000.0, 3, "test", 2).frames(0, 300)
    anywind._SCREEN_CACHE.clear()
    assert torch.equal(side_by_side, one_by_one)


@pytest.mark.physics
@pytest.mark.slow
def test_two_fine_samples_per_subaperture_keep_the_fitting_and_aliasing_terms_within_ten_percent():
    """The flagship samples the phase at 2 fine intervals per subaperture side (8x less synthesis than the default
    4). On the very same phase (synthesised at 4 samples, its every other point read at 2: the flagship's sky at 12
    across, 200 frames), the fitting error (the pupil's residual after the DM's fit) and the aliasing (the surface of
    ``R S phi - P F phi`` over the pupil) at 2 samples are within 10% of those at 4, both lower (the fit of fewer
    points leaves less of them: measured 8% and 6% at 12 across). Every contender shares both terms."""
    n_across, frames = 12, 200
    four, two = _sky(n_across, 4, frames), _sky(n_across, 2, frames)
    turbulence = four.turbulence(1, "test", 1)
    ops4, ops2 = turbulence.operators, loop_operators(two.grid, two.sensor.shack_hartmann())
    points4, points2 = (ops.sensor.geometry.fine_grid.positions_m for ops in (ops4, ops2))
    distance = np.hypot(*(points2[:, None, :] - points4[None, :, :]).transpose(2, 0, 1))
    subset = distance.argmin(1)
    assert distance[np.arange(len(points2)), subset].max() < 1e-9  # every point of 2 is a point of 4
    phase4 = turbulence.fine.frames(0, frames).reshape(-1, len(points4)).numpy()
    terms = {}
    for samples, ops, phase in ((4, ops4, phase4), (2, ops2, np.ascontiguousarray(phase4[:, subset]))):
        p = ops.products(phase)
        zero = torch.zeros_like(p["sum"])
        terms[samples] = (float(ops.pupil_rms(p["z"], p["sum"], p["sumsq"], -p["fit"]).median()),
                          float(ops.pupil_rms(torch.zeros_like(p["z"]), zero, zero, p["sensed"] - p["fit"]).median()))
    (fit_2, alias_2), (fit_4, alias_4) = terms[2], terms[4]
    assert 0.9 < fit_2 / fit_4 <= 1.0, terms
    assert 0.9 < alias_2 / alias_4 <= 1.0, terms
