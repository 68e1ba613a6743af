"""The coupled (neighbourhood) analysis beyond DENSE_LIMIT rows: ARPACK and Brent's method on small grids, checked
against the dense path (every eigenvalue, bisected edges), a closed form, and simulated bisection."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from eofnn.analysis import block
from eofnn.analysis.linear import dm_gain_margin
from eofnn.analysis.stability import LoopSetup, analyse
from eofnn.control.baselines import critical_gain
from eofnn.sim.grid import ActuatorGrid

NONE = torch.empty(0, dtype=torch.float64)


def _coupled_filter(kind: str, p: int, across: int = 6, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Random neighbourhood weights (radius 1.5 pitches) of a loop stable at the nominal DM gain: an open-loop
    filter (stable at g = g_model whatever its weights), or a closed-loop one near a leaky integrator."""
    grid = ActuatorGrid(2.0, across)
    neighbours = grid.neighbours(1.5)
    k_act, slots = neighbours.shape
    taps = p * (2 if kind == "closed_loop" else 1)
    gen = torch.Generator().manual_seed(seed)
    weights = 0.05 * torch.randn(k_act, slots, taps, generator=gen, dtype=torch.float64)
    own = (neighbours == torch.arange(k_act).unsqueeze(1)).int().argmax(1)
    if kind == "closed_loop":
        weights[torch.arange(k_act), own, 0] += 0.9
        weights[torch.arange(k_act), own, p] -= 0.3
    else:
        weights[torch.arange(k_act), own, 0] += 0.5
    return weights.reshape(k_act, -1), neighbours


def _counted(monkeypatch) -> list[int]:
    """Count the spectral radii computed (each is one eigenvalue problem)."""
    calls = [0]
    original = block.SpectralRadius.__call__

    def counted(self, p_list):
        calls[0] += 1
        return original(self, p_list)

    monkeypatch.setattr(block.SpectralRadius, "__call__", counted)
    return calls


@pytest.mark.slow
@pytest.mark.parametrize("kind, p, delay", [("open_loop", 3, 2), ("open_loop", 2, 2.5), ("closed_loop", 2, 2)])
def test_the_sparse_path_finds_the_dense_paths_margins_with_fewer_eigenvalue_problems(monkeypatch, kind, p, delay):
    weights, neighbours = _coupled_filter(kind, p)
    setup = LoopSetup(delay_frames=delay, controller_delay_frames=delay)
    calls = _counted(monkeypatch)
    dense = analyse(weights, kind, p, setup, structure="neighbourhood", neighbours=neighbours, frequencies_hz=NONE)
    dense_calls, calls[0] = calls[0], 0
    monkeypatch.setattr(block, "DENSE_LIMIT", 0)  # every companion through ARPACK, every edge by Brent's method
    sparse = analyse(weights, kind, p, setup, structure="neighbourhood", neighbours=neighbours, frequencies_hz=NONE)
    assert dense.stable and sparse.stable
    low, high = dense.gain_margin
    assert math.isfinite(low) and math.isfinite(high) and low < setup.dm_gain < high
    # (an open-loop filter at g = g_model has every pole at 0: rounding leaves them at ~1e-6, a nilpotent's root)
    assert float(sparse.max_root_modulus[0]) == pytest.approx(float(dense.max_root_modulus[0]), rel=1e-8, abs=1e-5)
    assert sparse.gain_margin == pytest.approx(dense.gain_margin, rel=1e-7)
    assert int(sparse.integer_delay_margin_frames[0]) == int(dense.integer_delay_margin_frames[0])
    assert float(sparse.delay_margin_frames[0]) == pytest.approx(float(dense.delay_margin_frames[0]), rel=1e-6)
    assert calls[0] < 0.6 * dense_calls, (calls[0], dense_calls)  # three bisections of 30 steps vs Brent's ~8


@pytest.mark.slow
def test_the_sparse_path_finds_the_coupled_integrators_closed_form(monkeypatch):
    """y = y(n-1) - k (I + e A) u: the modes of I + e A are integrators of gain k (1 + e lambda)."""
    grid = ActuatorGrid(2.0, 6)
    neighbours = grid.neighbours(1.0)
    k_act, slots = neighbours.shape
    gain, coupling = 0.4, 0.1
    weights = torch.zeros(k_act, slots, 2, dtype=torch.float64)
    weights[:, 0, 0] = 1.0
    weights[:, 0, 1] = -gain
    weights[:, 1:, 1] = -gain * coupling
    adjacency = np.zeros((k_act, k_act))
    for k in range(k_act):
        for j in neighbours[k, 1:].tolist():
            if j < k_act:
                adjacency[k, j] = 1.0
    largest = np.linalg.eigvalsh(np.eye(k_act) + coupling * adjacency).max()
    monkeypatch.setattr(block, "DENSE_LIMIT", 0)
    result = analyse(weights.flatten(1), "closed_loop", 1, LoopSetup(delay_frames=2), structure="neighbourhood",
                     neighbours=neighbours, frequencies_hz=NONE)
    assert result.gain_margin[1] == pytest.approx(critical_gain(2) / (gain * largest), rel=1e-8)


@pytest.mark.slow
def test_a_sequence_of_sparse_analyses_is_reproducible(monkeypatch):
    """ARPACK's first start vector is seeded, the later ones are the previous solve's: the same numbers every time."""
    weights, neighbours = _coupled_filter("open_loop", 3, seed=1)
    monkeypatch.setattr(block, "DENSE_LIMIT", 0)
    runs = [analyse(weights, "open_loop", 3, LoopSetup(), structure="neighbourhood", neighbours=neighbours,
                    frequencies_hz=NONE).to_dict() for _ in range(2)]
    runs[0]["analysis_seconds"] = runs[1]["analysis_seconds"] = 0
    assert runs[0] == runs[1]


@pytest.mark.slow
def test_the_margin_function_of_select_skips_the_delay_margin(monkeypatch):
    """optimization.select needs the DM-gain interval only: the delay scan is not run, the interval is the same."""
    weights, neighbours = _coupled_filter("open_loop", 3)
    calls = _counted(monkeypatch)
    full = analyse(weights, "open_loop", 3, LoopSetup(), structure="neighbourhood", neighbours=neighbours,
                   frequencies_hz=NONE)
    full_calls, calls[0] = calls[0], 0
    network = type("Net", (), {"structure": "neighbourhood", "neighbours": neighbours})()
    spec = type("Spec", (), {"delay_frames": 2, "kind": "open_loop", "history_length": 3})()
    assert dm_gain_margin()(network, weights, spec, 1.0, 1.0) == pytest.approx(full.gain_margin, rel=1e-12)
    assert calls[0] < full_calls
    alone = analyse(weights, "open_loop", 3, LoopSetup(), structure="neighbourhood", neighbours=neighbours,
                    frequencies_hz=NONE, delay_margin=False)
    assert math.isnan(float(alone.delay_margin_frames[0])) and int(alone.integer_delay_margin_frames[0]) == -1
    per_actuator = analyse(weights[:, :3], "open_loop", 3, LoopSetup(), delay_margin=False)
    assert per_actuator.gain_margin == analyse(weights[:, :3], "open_loop", 3, LoopSetup()).gain_margin
    assert bool(per_actuator.delay_margin_frames.isnan().all())


def test_a_coupled_analysis_that_does_not_fit_memory_is_refused_before_it_runs(monkeypatch):
    """One line, as an analysis too large (so compare reports no analytic margins instead of stopping)."""
    import eofnn.resources

    weights, neighbours = _coupled_filter("open_loop", 3)
    monkeypatch.setattr(eofnn.resources, "available_memory_bytes", lambda: 2**20)
    monkeypatch.setattr(block, "matrix_polynomials", lambda *a, **k: pytest.fail("the analysis started"))
    with pytest.raises(block.CoupledAnalysisTooLarge, match=r"analysis of a neighbourhood filter on 32 actuators \(9 "
                       r"neighbours each, block companions up to 448 rows\) needs about .* GiB of memory"):
        analyse(weights, "open_loop", 3, LoopSetup(), structure="neighbourhood", neighbours=neighbours)


def test_a_spectral_radius_that_does_not_converge_is_one_line(monkeypatch):
    weights, neighbours = _coupled_filter("open_loop", 3)
    monkeypatch.setattr(block, "DENSE_LIMIT", 0)
    monkeypatch.setattr(block, "_largest_eigenvalues", lambda *a: (np.zeros(0), np.zeros((0, 0))))
    with pytest.raises(block.CoupledAnalysisUnavailable, match=r"did not converge .* Krylov spaces of 60 and 120\)"):
        analyse(weights, "open_loop", 3, LoopSetup(dm_gain=1.1), structure="neighbourhood", neighbours=neighbours)


@pytest.mark.slow
@pytest.mark.physics
def test_the_sparse_analytic_interval_matches_simulated_bisection(monkeypatch, small_scenario):
    """A fitted neighbourhood EOF: the interval of the sparse path (forced on this small grid) and the closed-loop
    bisection of ``compare --simulated_margins`` agree within its tolerance, 0.05."""
    from eofnn.evaluation.config import EvaluationConfig
    from eofnn.evaluation.experiment import Experiment
    from eofnn.evaluation.margins import simulated_dm_gain_interval

    predictors = {"nb": {"history_length": 3, "data": {"frames": 1500, "val_frames": 500, "sequence_frames": 1500},
                         "network": {"class_path": "eofnn.models.linear.LinearFilter",
                                     "init_args": {"structure": "neighbourhood", "radius": 1.5}}}}
    experiment = Experiment(small_scenario.with_plant(wfs_noise_nm=1.0), {"nominal": {}}, predictors,
                            EvaluationConfig(frames=1000, settle_frames=200), log=lambda _: None)
    monkeypatch.setattr(block, "DENSE_LIMIT", 0)
    low, high = experiment.stability("nb", "nominal")["dm_gain_interval"]
    simulated = simulated_dm_gain_interval(experiment, "nb", "nominal", tolerance=0.05)
    sim_low, sim_high = simulated["dm_gain_interval"]
    assert 0.5 < low < 1 < high < 2
    assert abs(sim_low - low) <= 0.05 and abs(sim_high - high) <= 0.05, (low, high, simulated)
