"""Benchmark: the analytic DM-gain interval of a neighbourhood (coupled) filter, against the method it replaced.

``coupled/<K>x<taps>``: an open-loop neighbourhood EOF (radius 1.5 pitches) fitted in configs/realistic.yaml's
scenario on an ``n_across`` grid at the same pitch (40 across: 1264 actuators), its DM-gain interval found by
:func:`eofnn.analysis.stability.analyse` (``delay_margin=False``: what ``optimization.select`` asks for; beyond
``DENSE_LIMIT`` companion rows, ARPACK started from the previous solve's eigenvector and Brent's method on the
spectral radius), against the same interval found as eofnn found it before (the same bracketing steps, then 30
bisections of stable / unstable, each radius a fresh ARPACK solve of 6 eigenvalues in its default Krylov space; one
BLAS thread for both).
``coupled/<K>x<taps>/budget``: the same time against a budget (goal: the interval in minutes). ``info`` holds both
intervals and their largest difference.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spla
import torch
from threadpoolctl import threadpool_limits

from benchmarks.bench_turbulence import scenario_with_grid
from benchmarks.common import Row, Timing, time_interleaved
from eofnn.analysis import block
from eofnn.analysis.stability import LoopSetup, analyse
from eofnn.data.stream import DataConfig
from eofnn.sim.scenario import Scenario
from eofnn.training.fit import fit_predictor

REALISTIC = Path(__file__).resolve().parent.parent / "configs" / "realistic.yaml"


def fitted_neighbourhood_filter(n_across: int, history_length: int, train_frames: int, val_frames: int,
                                seed: int = 0):
    """``(weights, neighbours, spec)`` of an open-loop neighbourhood EOF fitted (``alpha: auto``, simulator truth)
    in the realistic scenario on an ``n_across`` grid at its pitch."""
    base = Scenario.from_yaml(REALISTIC)
    scenario = scenario_with_grid(base, n_across, base.grid.diameter_m * n_across / base.grid.n_across)
    network = {"class_path": "eofnn.models.linear.LinearFilter",
               "init_args": {"structure": "neighbourhood", "radius": 1.5}}
    result = fit_predictor(scenario, "open_loop", history_length, network,
                           data=DataConfig(frames=train_frames, val_frames=val_frames, sequence_frames=train_frames,
                                           seed=seed))
    net = result.predictor.network
    return net.weight.detach(), net.neighbours, result.predictor.spec


def _former_radius(p_list) -> float:
    """The spectral radius as computed before: dense up to DENSE_LIMIT rows, else ARPACK (6 eigenvalues, its default
    Krylov space and its own random start), here on one BLAS thread like eofnn's (on 2 busy cores, 2 threads made
    either several times slower): the ratio is the method's, not the threads'."""
    matrix = block.companion(p_list)
    if matrix is None:
        return 0.0
    if matrix.shape[0] <= block.DENSE_LIMIT:
        return float(np.abs(np.linalg.eigvals(matrix.toarray())).max())
    with threadpool_limits(1, user_api="blas"):  # as eofnn's solves now run (threads only slow them down)
        try:
            values = spla.eigs(matrix, k=6, which="LM", return_eigenvectors=False, tol=1e-10, maxiter=20000)
        except spla.ArpackNoConvergence as err:
            values = err.eigenvalues
    return float(np.abs(values).max())


def former_gain_interval(weights: torch.Tensor, neighbours: torch.Tensor, spec, setup: LoopSetup) -> tuple:
    """The DM-gain interval as eofnn found it before: bracketing steps, then 30 bisections per edge."""
    d_list, n_list = block.matrix_polynomials(weights, neighbours, spec.kind, spec.history_length,
                                              setup.dm_gain_model, setup.controller_delay)
    plant = setup.plant_polynomial().numpy()

    def stable_at(gain: float) -> bool:
        return _former_radius(block.characteristic(d_list, n_list, plant, gain)) < 1

    def edge(steps) -> float:
        previous = setup.dm_gain
        for candidate in (setup.dm_gain * s for s in steps):
            if not stable_at(candidate):
                lo, hi = previous, candidate
                for _ in range(block.BISECTIONS):
                    mid = 0.5 * (lo + hi)
                    lo, hi = (mid, hi) if stable_at(mid) else (lo, mid)
                return 0.5 * (lo + hi)
            previous = candidate
        return math.inf if steps[-1] > 1 else -math.inf

    return edge(block.GAIN_STEPS_DOWN), edge(block.GAIN_STEPS_UP)


def coupled_rows(n_across: int = 40, history_length: int = 10, train_frames: int = 4000, val_frames: int = 1000,
                 repeat: int = 1, seed: int = 0, budget_seconds: float = 300.0) -> list[Row]:
    """The two ``coupled/<K>x<taps>`` rows (module docstring); no untimed warm-up (a timing is minutes)."""
    weights, neighbours, spec = fitted_neighbourhood_filter(n_across, history_length, train_frames, val_frames, seed)
    setup = LoopSetup(delay_frames=spec.delay_frames, controller_delay_frames=spec.delay_frames)
    results = {}

    def run_eofnn():
        results["eofnn"] = analyse(weights, spec.kind, spec.history_length, setup, structure="neighbourhood",
                                   neighbours=neighbours, frequencies_hz=torch.empty(0, dtype=torch.float64),
                                   delay_margin=False).gain_margin

    def run_former():
        results["former"] = former_gain_interval(weights, neighbours, spec, setup)

    timings = time_interleaved({"eofnn": (run_eofnn, 1), "former": (run_former, 1)}, repeat, warmup=0)
    k_act = neighbours.shape[0]
    rows = block.companion_rows(k_act, spec.kind, spec.history_length, setup.delay_frames, setup.controller_delay)
    info = {"n_actuators": k_act, "neighbours": neighbours.shape[1], "taps": spec.history_length, "kind": spec.kind,
            "companion_rows": rows, "dm_gain_interval": list(results["eofnn"]),
            "former_dm_gain_interval": list(results["former"]),
            "max_interval_difference": max(abs(a - b) for a, b in zip(results["eofnn"], results["former"],
                                                                      strict=True)),
            "computes": "the DM-gain interval (no delay margin, no transfer functions) of a fitted open-loop "
                        "neighbourhood EOF"}
    name = f"coupled/{k_act}x{spec.history_length}"
    return [Row("stability", name, "s/interval", timings["eofnn"], timings["former"],
                "former bisection (30 steps per edge, fresh 6-eigenvalue ARPACK solves)", None, "", "cpu", info),
            Row("stability", f"{name}/budget", "s/interval", timings["eofnn"], Timing([budget_seconds]),
                f"{budget_seconds:g} s budget", 1.0, f">= 1 (interval < {budget_seconds:g} s)", "cpu", info)]
