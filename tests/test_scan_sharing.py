"""Issue 47: compare shares the loops its contenders run alike (:mod:`eofnn.evaluation.sharing`) and the slope noise
every loop on a stream draws again (:func:`eofnn.sim.loop.readings.reconstructed_noise`), and no number moves.

The tiny flagship (tests/conf/flagship_tiny.yaml: its guard deploys the EOF whole) runs twice in one process, once
with nothing shared and no noise kept, once as compare runs it: every number of both, the loops' time series
included, is the same bit for bit, and the shared run closes fewer loops by exactly the guard's gain scan and the
guarded contender's scored loops (its test loop and its error budget's two)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
import yaml

from eofnn.control import modal
from eofnn.evaluation.config import EvaluationConfig
from eofnn.evaluation.experiment import Experiment
from eofnn.sim.loop import readings, runner
from eofnn.sim.scenario import Scenario

TINY = Path(__file__).parent / "conf" / "flagship_tiny.yaml"
GUARDED = "ol_eof_aa_guarded"


def _run(share: bool, monkeypatch: pytest.MonkeyPatch) -> dict:
    """The tiny flagship's experiment, sharing or not: its result, the loops it closed, the noise it drew and reused."""
    config = yaml.safe_load(TINY.read_text())
    loops = []

    class CountedLoop(runner.Loop):
        def __init__(self, *args, **kwargs):
            loops.append(1)
            super().__init__(*args, **kwargs)

    readings.clear_noise_cache()
    with monkeypatch.context() as patch:
        patch.setattr(runner, "Loop", CountedLoop)
        patch.setattr(modal, "_RECORDED", {})  # each run records the LQG's telemetry itself
        patch.setattr(readings, "NOISE_CACHE_BYTES", readings.NOISE_CACHE_BYTES if share else 0)
        torch.manual_seed(0)
        experiment = Experiment(Scenario.from_dict(config["scenario"]), config["scenarios"], config["predictors"],
                                EvaluationConfig(**config["evaluation"]), log=lambda _: None, share_loops=share)
        result = experiment.run()
    noise = dict(readings.NOISE_STATS)
    readings.clear_noise_cache()
    return {"result": result, "loops": len(loops), "noise": noise, "reused": dict(experiment.sharing.reused)}


@pytest.fixture(scope="module")
def runs():
    with pytest.MonkeyPatch.context() as monkeypatch:
        alone = _run(False, monkeypatch)
        shared = _run(True, monkeypatch)
    return alone, shared


def _numbers(run: dict) -> str:
    """Every number of a run as text (floats by repr, so equal text is equal bits): metrics.json's (timings and
    memory left out) and each contender's whole :class:`~eofnn.evaluation.metrics.LoopMetrics` (time series too)."""
    result = run["result"]
    summary = {k: v for k, v in result.to_json().items() if k not in ("timings_s", "peak_memory_bytes")}
    series = {s: {p: dataclasses.asdict(m) for p, m in preds.items()} for s, preds in result.metrics.items()}
    return json.dumps({"summary": summary, "series": series}, sort_keys=True, default=repr)


@pytest.mark.slow
def test_sharing_moves_no_number(runs):
    alone, shared = runs
    assert _numbers(shared) == _numbers(alone)
    # The guard deployed the EOF whole: the case whose loops are shared (its metrics are its twin's).
    assert shared["result"].fallbacks["nominal"][GUARDED]["deployed"] == "predictor"
    assert _numbers(shared).count('"median_rms_nm"') > 0


@pytest.mark.slow
def test_the_guard_reuses_the_integrators_scan_and_its_twins_loops(runs):
    alone, shared = runs
    assert alone["reused"] == {} and alone["noise"]["reused"] == 0
    # One gain scan (the guard's is the integrator's), one contender's loops, the fitting error of the test stream
    # for every contender but the first and the guarded one.
    assert shared["reused"] == {"gain_scan": 1, "scored": 1, "fitting": 3}
    guard_scan = shared["result"].fallbacks["nominal"][GUARDED]["gain_scan"]
    assert guard_scan == shared["result"].integrator_gains["nominal"]["integrator"]["scanned"]
    # Not closed again: each gain of the guard's scan (refinements included), and the guarded contender's test loop
    # with the error budget's noise-free and perfect runs.
    assert alone["loops"] - shared["loops"] == len(guard_scan) + 3


@pytest.mark.slow
def test_loops_on_one_stream_draw_their_noise_once(runs):
    alone, shared = runs
    guard_scan = shared["result"].fallbacks["nominal"][GUARDED]["gain_scan"]
    # Every chunk of a noisy loop asks for its noise: alone, each draws it; shared, only the first loop on a stream
    # does, the others find it. The shared run asks less by the loops it does not close (each a chunk): the guard's
    # scan and the guarded contender's test loop (the error budget's runs are noise-free).
    assert shared["noise"]["reused"] > shared["noise"]["drawn"] > 0
    assert alone["noise"]["drawn"] == shared["noise"]["drawn"] + shared["noise"]["reused"] + len(guard_scan) + 1


def test_kept_noise_is_the_noise_drawn_and_leaves_the_generator_where_drawing_does():
    """A loop that finds its noise kept gets the very tensor drawn, and its generator goes on as if it had drawn."""
    scenario = Scenario.from_dict({**yaml.safe_load(TINY.read_text())["scenario"]})
    turbulence = scenario.turbulence(0, "test", 2)
    reconstructor = turbulence.operators.reconstructor
    readings.clear_noise_cache()
    drawn_generator = torch.Generator().manual_seed(5)
    first = readings.reconstructed_noise(turbulence, (2, 30), 3.0, reconstructor, drawn_generator)
    kept_generator = torch.Generator().manual_seed(5)
    again = readings.reconstructed_noise(turbulence, (2, 30), 3.0, reconstructor, kept_generator)
    assert again is first and readings.NOISE_STATS == {"drawn": 1, "reused": 1}
    assert torch.equal(kept_generator.get_state(), drawn_generator.get_state())
    plain = torch.Generator().manual_seed(5)
    assert torch.equal(first, turbulence.slope_noise((2, 30), 3.0, plain) @ reconstructor.T)
    # Another RMS, shape or generator state is other noise.
    assert readings.reconstructed_noise(turbulence, (2, 30), 2.0, reconstructor, torch.Generator().manual_seed(5)) \
        is not first
    assert readings.reconstructed_noise(turbulence, (2, 30), 3.0, reconstructor, kept_generator) is not first
    assert readings.reconstructed_noise(turbulence, (2, 30), 0.0, reconstructor, kept_generator) is None
    readings.clear_noise_cache()
