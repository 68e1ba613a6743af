"""Benchmark 4: fit + evaluate on a small reference-like scenario, eofnn against a numpy/HCIPy script."""

from __future__ import annotations

import time

import numpy as np

from benchmarks.baselines import HcipyTurbulence, NumpyPredictiveLoop, numpy_lstsq_per_actuator, open_loop_regression
from benchmarks.bench_turbulence import scenario_with_grid
from benchmarks.common import Row, Timing, time_interleaved
from eofnn.data.history import HistorySpec
from eofnn.data.stream import DataConfig
from eofnn.sim.loop.runner import run_loop
from eofnn.sim.scenario import Scenario
from eofnn.training.fit import fit_predictor


def eofnn_pipeline(scenario: Scenario, spec: HistorySpec, train_frames: int, val_frames: int, eval_frames: int,
                   seed: int, out: dict) -> None:
    """``fit_predictor`` then ``run_loop`` with the fitted controller; timings and results go to ``out``."""
    t0 = time.perf_counter()
    result = fit_predictor(scenario, spec.kind, spec.history_length,
                           data=DataConfig(frames=train_frames, val_frames=val_frames, seed=seed))
    t1 = time.perf_counter()
    loop = run_loop(scenario.turbulence(seed, "test"), scenario.plant, result.predictor.controller(), eval_frames,
                    record=(), progress=False)
    t2 = time.perf_counter()
    out.setdefault("fit", []).append(t1 - t0)
    out.setdefault("evaluate", []).append(t2 - t1)
    out["val_loss"] = result.val_loss
    out["residual_rms_nm"] = float(loop.residual_rms_nm[0, spec.first_frame:].mean())
    out["diverged"] = loop.diverged


def script_pipeline(scenario: Scenario, spec: HistorySpec, train_frames: int, val_frames: int, eval_frames: int,
                    seed: int, out: dict) -> None:
    """The same work written plainly: HCIPy frames, one ``lstsq`` per actuator, a numpy closed loop."""
    p, d = spec.history_length, spec.delay_frames
    t0 = time.perf_counter()
    train = HcipyTurbulence(scenario.atmosphere, scenario.grid, scenario.frame_rate_hz, seed).frames(train_frames)
    x, target = open_loop_regression(train, p, d)
    weights = numpy_lstsq_per_actuator(x, target)
    val = HcipyTurbulence(scenario.atmosphere, scenario.grid, scenario.frame_rate_hz, seed + 1).frames(val_frames)
    xv, tv = open_loop_regression(val, p, d)
    val_loss = float((((xv * weights).sum(-1) - tv) ** 2).mean())
    t1 = time.perf_counter()
    test = HcipyTurbulence(scenario.atmosphere, scenario.grid, scenario.frame_rate_hz, seed + 2).frames(eval_frames)
    rms = NumpyPredictiveLoop(weights, "open_loop", p, d).run(test)
    t2 = time.perf_counter()
    out.setdefault("fit", []).append(t1 - t0)
    out.setdefault("evaluate", []).append(t2 - t1)
    out["val_loss"] = val_loss
    out["residual_rms_nm"] = float(np.mean(rms[spec.first_frame:]))


def small_reference_scenario(reference: Scenario, diameter_m: float = 4.0, n_across: int = 20) -> Scenario:
    """The reference scenario on a smaller telescope at the same actuator pitch (same atmosphere and plant)."""
    return scenario_with_grid(reference, n_across, diameter_m)


def bench_end_to_end(scenario: Scenario, history_length: int = 4, train_frames: int = 20000,
                     val_frames: int = 2000, eval_frames: int = 5000, repeat: int = 2, warmup: int = 1,
                     seed: int = 0) -> list[Row]:
    """Seconds of the whole fit + evaluate pipeline, eofnn against the numpy/HCIPy script (goal: faster).

    Rows: ``total`` (goal ``>= 1``), and its two parts ``fit`` (training data, fit, validation) and ``evaluate``
    (closed loop on fresh test turbulence), each ``script / eofnn``. ``info`` carries the validation loss and the
    closed-loop residual RMS of both, which should be alike (they fit the same filter on different draws).
    """
    spec = HistorySpec("open_loop", history_length, scenario.delay_frames)
    eofnn_out: dict = {}
    script_out: dict = {}
    args = (scenario, spec, train_frames, val_frames, eval_frames, seed)
    time_interleaved({"eofnn": (lambda: eofnn_pipeline(*args, eofnn_out), 1),
                      "script": (lambda: script_pipeline(*args, script_out), 1)}, repeat=repeat, warmup=warmup)
    if eofnn_out["diverged"]:
        raise RuntimeError("the fitted eofnn predictor diverged in the end-to-end loop")
    # Drop the warm-up calls (the first entries) as time_interleaved does.
    parts = {name: (Timing(eofnn_out[name][warmup:]), Timing(script_out[name][warmup:]))
             for name in ("fit", "evaluate")}
    total = tuple(Timing([a + b for a, b in zip(out["fit"][warmup:], out["evaluate"][warmup:], strict=True)])
                  for out in (eofnn_out, script_out))
    info = {"n_across": scenario.grid.n_across, "diameter_m": scenario.grid.diameter_m,
            "n_actuators": scenario.grid.n_actuators, "history": spec.to_dict(), "train_frames": train_frames,
            "val_frames": val_frames, "eval_frames": eval_frames,
            "eofnn_val_loss_nm2": eofnn_out["val_loss"], "script_val_loss_nm2": script_out["val_loss"],
            "eofnn_residual_rms_nm": eofnn_out["residual_rms_nm"],
            "script_residual_rms_nm": script_out["residual_rms_nm"]}
    return [
        Row("end_to_end", "total", "s/run", total[0], total[1], "numpy/HCIPy script", goal_ratio=1.0,
            goal_label=">= 1 (faster than the script)", info=info),
        Row("end_to_end", "fit", "s/run", *parts["fit"], "numpy/HCIPy script (frames + lstsq + validation)",
            info=info),
        Row("end_to_end", "evaluate", "s/run", *parts["evaluate"], "numpy/HCIPy script (frames + numpy loop)",
            info=info),
    ]
