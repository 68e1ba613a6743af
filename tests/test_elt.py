"""ELT-class sizes on one machine: shared any-wind screens, the coupled analysis's size, refusals before anything runs.

Everything here runs on small grids (10 actuators across) in seconds; configs/elt_small.yaml is only parsed.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from eofnn.analysis import block
from eofnn.analysis.stability import LoopSetup, analyse
from eofnn.sim.atmosphere import anywind
from eofnn.sim.atmosphere.turbulence import Atmosphere, Layer
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.loop.plant import Plant
from eofnn.sim.scenario import Scenario

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _oblique_scenario(screen_frames: int = 256) -> Scenario:
    return Scenario(grid=ActuatorGrid(2.0, 10),
                    atmosphere=Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=10.0,
                                          layers=[Layer(0.6, 20.0, 30.0), Layer(0.4, 15.0, 150.0)],
                                          screen_frames=screen_frames),
                    plant=Plant(delay_frames=2))


@pytest.mark.slow
def test_any_wind_screens_are_built_once_per_realisation_and_shared(monkeypatch):
    monkeypatch.setattr(anywind, "_SCREEN_CACHE", {})
    scenario = _oblique_scenario()
    first = scenario.turbulence(3, "test")
    again = scenario.turbulence(3, "test")
    other = scenario.turbulence(3, "train")
    assert all(a is b for a, b in zip(first._strips[0], again._strips[0], strict=True))  # one build, shared
    assert not any(a is b for a, b in zip(first._strips[0], other._strips[0], strict=True))
    frames = first.frames(0, 200)
    assert torch.equal(frames, again.frames(0, 200))
    assert not torch.allclose(frames, other.frames(0, 200))
    # Without the cache (a budget of nothing) the same seed rebuilds the same screen, bit for bit.
    monkeypatch.setattr(anywind, "_SCREEN_CACHE", {})
    monkeypatch.setattr(anywind, "_SCREEN_CACHE_BYTES", 0)
    rebuilt = scenario.turbulence(3, "test")
    assert not anywind._SCREEN_CACHE
    assert torch.equal(frames, rebuilt.frames(0, 200))


@pytest.mark.slow
def test_the_screen_cache_keeps_within_its_budget(monkeypatch):
    monkeypatch.setattr(anywind, "_SCREEN_CACHE", {})
    one = _oblique_scenario().turbulence(0, "a")._strips[0][0].screen_nbytes
    monkeypatch.setattr(anywind, "_SCREEN_CACHE_BYTES", 3 * one)  # room for three screens of this size
    for stream in ("a", "b", "c"):  # two layers each
        _oblique_scenario().turbulence(0, stream)
    assert 0 < sum(lay.screen_nbytes for lay in anywind._SCREEN_CACHE.values()) <= 3 * one
    assert len(anywind._SCREEN_CACHE) == 3


def _self_slot(neighbours: torch.Tensor) -> torch.Tensor:
    """Column of each actuator's own entry in its neighbourhood table."""
    own = neighbours == torch.arange(len(neighbours)).unsqueeze(1)
    assert bool((own.sum(1) == 1).all())
    return own.int().argmax(1)


@pytest.mark.slow
@pytest.mark.parametrize("kind, p, delay", [("closed_loop", 3, 2), ("open_loop", 4, 2), ("open_loop", 3, 3),
                                            ("open_loop", 4, 1.5), ("closed_loop", 3, 2.5)])
def test_an_uncoupled_neighbourhood_filter_has_the_per_actuator_margins(kind, p, delay):
    """The per-actuator (block-diagonal: K scalar loops) analysis and the coupled one agree when nothing couples."""
    grid = ActuatorGrid(2.0, 5)
    k_act, taps = grid.n_actuators, p * (2 if kind == "closed_loop" else 1)
    gen = torch.Generator().manual_seed(1)
    own = 0.02 * torch.randn(k_act, taps, generator=gen, dtype=torch.float64)
    if kind == "closed_loop":
        own[:, 0] += 1.0  # an integrator with a spread of gains, plus small random taps
        own[:, p] -= 0.3 + 0.2 * torch.rand(k_act, generator=gen, dtype=torch.float64)
    else:
        own[:, 0] += 0.6 + 0.3 * torch.rand(k_act, generator=gen, dtype=torch.float64)
    neighbours = grid.neighbours(1.5)
    coupled = torch.zeros(k_act, neighbours.shape[1], taps, dtype=torch.float64)
    coupled[torch.arange(k_act), _self_slot(neighbours)] = own
    setup = LoopSetup(delay_frames=delay, dm_gain=1.3, controller_delay_frames=delay)
    scalar = analyse(own, kind, p, setup)
    full = analyse(coupled.reshape(k_act, -1), kind, p, setup, structure="neighbourhood", neighbours=neighbours)
    assert scalar.stable and full.stable
    assert float(full.max_root_modulus[0]) == pytest.approx(float(scalar.max_root_modulus.max()), rel=1e-8)
    assert full.gain_margin == pytest.approx(scalar.gain_margin, rel=1e-6)
    assert int(full.integer_delay_margin_frames[0]) == int(scalar.integer_delay_margin_frames.min())
    assert float(full.delay_margin_frames[0]) == pytest.approx(float(scalar.delay_margin_frames.min()), rel=1e-6)


@pytest.mark.parametrize("kind, p, delay, controller_delay", [
    ("closed_loop", 5, 2, 2), ("open_loop", 4, 2, 2), ("open_loop", 3, 2.5, 2.5), ("open_loop", 4, 3, 2),
    ("closed_loop", 2, 4, 4)])
def test_companion_rows_counts_the_block_companion(kind, p, delay, controller_delay):
    grid = ActuatorGrid(2.0, 6)
    neighbours = grid.neighbours(1.0)
    taps = p * (2 if kind == "closed_loop" else 1)
    weights = 0.1 + torch.rand(grid.n_actuators, neighbours.shape[1] * taps, dtype=torch.float64,
                               generator=torch.Generator().manual_seed(0))
    setup = LoopSetup(delay_frames=delay, dm_gain=1.7, controller_delay_frames=controller_delay)
    d_list, n_list = block.matrix_polynomials(weights, neighbours, kind, p, 1.0, setup.controller_delay)
    p_list = block.characteristic(d_list, n_list, setup.plant_polynomial().numpy(), setup.dm_gain)
    rows = block.companion_rows(grid.n_actuators, kind, p, delay, controller_delay)
    assert rows == grid.n_actuators * (len(p_list) - 1)


def test_a_coupled_analysis_beyond_the_limit_is_refused_with_its_size(monkeypatch):
    grid = ActuatorGrid(2.0, 10)
    neighbours = grid.neighbours(1.5)
    weights = torch.zeros(grid.n_actuators, neighbours.shape[1] * 4, dtype=torch.float64)
    monkeypatch.setattr(block, "COMPANION_LIMIT", 100)
    rows = block.companion_rows(grid.n_actuators, "open_loop", 4, 2, 2)
    with pytest.raises(block.CoupledAnalysisTooLarge,
                       match=rf"on {grid.n_actuators} actuators needs a {rows}-row block companion .* more than the "
                             r"100 it handles"):
        analyse(weights, "open_loop", 4, LoopSetup(), structure="neighbourhood", neighbours=neighbours)


def test_the_elt_grid_is_beyond_the_coupled_limit_but_40_across_with_12_taps_and_per_actuator_are_not():
    k_act = ActuatorGrid(39.0, 80).n_actuators
    assert k_act == 5024
    assert block.companion_rows(k_act, "open_loop", 4, 2, 2) > block.COMPANION_LIMIT
    assert block.companion_rows(ActuatorGrid(8.0, 40).n_actuators, "closed_loop", 5, 2, 2) <= block.COMPANION_LIMIT
    # Issue 31: an open-loop neighbourhood filter at 40 across with 10-12 taps, integer or fractional delay.
    assert block.companion_rows(ActuatorGrid(8.0, 40).n_actuators, "open_loop", 12, 2.5, 2.5) <= block.COMPANION_LIMIT


@pytest.mark.cli
@pytest.mark.slow
@pytest.mark.parametrize("change, key", [("wind_direction_deg: .nan", "wind_direction_deg=nan"),
                                         ("wind_direction_deg: .inf", "wind_direction_deg=inf"),
                                         ("wind_speed_mps: .nan", "wind_speed_mps=nan"),
                                         ("wind_speed_mps: -.inf", "wind_speed_mps=-inf")])
def test_a_non_finite_wind_change_is_refused(cli_error, tmp_path, change, key):
    line = cli_error(["compare", "--config", CONFIGS / "elt_small.yaml", "--scenario.atmosphere.changes",
                      f"[{{at_s: 0.5, layer: 1, {change}}}]", "--out", tmp_path / "o"], key, tmp_path / "o")
    assert "finite" in line


GIB = 2**30


@pytest.mark.cli
@pytest.mark.slow
@pytest.mark.parametrize("args, expected", [
    (["--scenario.atmosphere.screen_frames", "1000000"], "exact screens of non-lattice winds (3 screen(s) of 5024 "
                                                          "actuators x screen_frames=1000000) needs about"),
    (["--evaluation.realisations", "8"], "evaluation.frames=2000: the set of exact screens of non-lattice winds (24 screen(s)"),
    (["--scenario.grid.n_across", "400"], "of memory"),
])
def test_an_elt_size_that_does_not_fit_memory_is_refused_before_anything_runs(cli_error, tmp_path, monkeypatch, args,
                                                                              expected):
    """On a machine with 4 GiB available (whatever this one has), with the number needed and what is allowed."""
    import eofnn.resources

    monkeypatch.setattr(eofnn.resources, "available_memory_bytes", lambda: 4 * GIB)
    def never(*args, **kwargs):
        raise AssertionError("a screen was built before the refusal")

    monkeypatch.setattr(anywind.AnyWindFrozenFlow, "__init__", never)
    line = cli_error(["compare", "--config", CONFIGS / "elt_small.yaml", *args, "--out", tmp_path / "o"],
                     expected, tmp_path / "o")
    needed = float(line.split("needs about ")[1].split(" GiB")[0]) if "GiB of memory" in line else math.inf
    assert needed > 0.8 * 4 and "3.2 GiB available" in line


def test_replay_in_blocks_of_frames_equals_one_block(monkeypatch, small_scenario):
    """A neighbourhood filter is replayed a few frames at a time (its gathered history is (frames, K, M x taps)):
    the same errors as all frames at once."""
    from eofnn.control.baselines import Integrator
    from eofnn.data.history import HistorySpec
    from eofnn.evaluation import replay as replay_module
    from eofnn.models.linear import LinearFilter
    from eofnn.sim.loop.runner import run_loop

    scen = small_scenario
    telemetry = run_loop(scen.turbulence(4, "test"), scen.plant, Integrator(0.5), 400).telemetry
    spec = HistorySpec("closed_loop", 3, 2)
    grid = {"diameter_m": scen.grid.diameter_m, "n_across": scen.grid.n_across, "obstruction": scen.grid.obstruction}
    network = LinearFilter(scen.grid.n_actuators, spec.n_taps, structure="neighbourhood", radius=1.5, grid=grid)
    with torch.no_grad():
        network.weight.normal_(0.0, 0.05, generator=torch.Generator().manual_seed(0))
    whole = replay_module.replay(network, spec, telemetry, plant={}, settle_frames=50)
    monkeypatch.setattr(replay_module, "REPLAY_BLOCK_ELEMENTS", 7 * scen.grid.n_actuators * spec.n_taps)
    blocks = replay_module.replay(network, spec, telemetry, plant={}, settle_frames=50)
    assert blocks.predictor.median_rms_nm == pytest.approx(whole.predictor.median_rms_nm, rel=1e-12)
    assert blocks.predictor.map_rms_nm == pytest.approx(whole.predictor.map_rms_nm, rel=1e-12)
    assert whole.predictor.median_rms_nm > 0
