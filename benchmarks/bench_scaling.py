"""Benchmark 5: how turbulence generation, the loop step and the fit grow with actuators, history and frames."""

from __future__ import annotations

import torch

from benchmarks.bench_fit import streamed_fit, synthetic_regression
from benchmarks.bench_loop import ContinuingTurbulence, integrator_like_filter
from benchmarks.bench_turbulence import scenario_with_grid
from benchmarks.common import Series, time_interleaved
from eofnn.control import PredictiveController
from eofnn.data.history import HistorySpec
from eofnn.sim.loop.runner import LoopInput, run_loop
from eofnn.sim.scenario import Scenario

#: "Linear" allows some slack for noise and cache effects.
LINEAR = 1.15
LINEAR_LABEL = "<= 1.15 (at most linear)"


def _turbulence_frame_s(turbulence: ContinuingTurbulence, n_frames: int, chunk: int, repeat: int) -> float:
    """Steady-state seconds per frame of streaming ``n_frames`` frames in ``Turbulence.frames`` calls of ``chunk``."""
    def stream():
        for _ in range(0, n_frames, chunk):
            turbulence.take(chunk)

    n = -(-n_frames // chunk) * chunk
    return time_interleaved({"t": (stream, n)}, repeat=repeat, warmup=1)["t"].min


def _step_s(n_actuators: int, spec: HistorySpec, steps: int, repeat: int, seed: int) -> float:
    """Seconds per ``PredictiveController.step`` (closed-loop EOF)."""
    controller = PredictiveController(integrator_like_filter(n_actuators, spec, seed=seed), spec)
    wfs = torch.randn(1, n_actuators, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    inp = LoopInput(0, wfs, wfs)

    def run():
        controller.reset(1, n_actuators, spec.delay_frames, torch.float64)
        for _ in range(steps):
            controller.step(inp)

    return time_interleaved({"s": (run, steps)}, repeat=repeat, warmup=1)["s"].min


def _run_loop_s(scenario: Scenario, turbulence: ContinuingTurbulence, spec: HistorySpec, n_frames: int,
                repeat: int, seed: int) -> float:
    """Seconds per frame of ``run_loop`` (turbulence generated as it goes) with a closed-loop EOF."""
    net = integrator_like_filter(scenario.grid.n_actuators, spec, seed=seed)

    def run():
        run_loop(turbulence, scenario.plant, PredictiveController(net, spec), n_frames, record=(), progress=False)

    return time_interleaved({"l": (run, n_frames)}, repeat=repeat, warmup=1)["l"].min


def _fit_s(x: torch.Tensor, t: torch.Tensor, batch_frames: int, repeat: int) -> float:
    """Seconds per streamed closed-form fit."""
    fit = (lambda: streamed_fit(x, t, batch_frames, 1e-9), 1)
    return time_interleaved({"f": fit}, repeat=repeat, warmup=1)["f"].min


def bench_scaling(scenario: Scenario, n_across: tuple[int, ...] = (20, 40, 80), histories: tuple[int, ...] = (4, 8, 16),
                  turbulence_frames: tuple[int, ...] = (10240, 20480, 40960), stream_chunk: int = 1024,
                  call_frames: tuple[int, ...] = (1000, 2000, 4000, 8000, 16000), chunk_frames: int = 20480,
                  loop_frames: int = 1000, steps: int = 1000, fit_frames: tuple[int, ...] = (10000, 20000, 40000),
                  fit_actuator_frames: int = 5000, fit_history_frames: int = 10000, fit_taps: int = 12,
                  batch_frames: int = 256, base_across: int = 40, loop_history: int = 12, repeat: int = 3,
                  compare_across: tuple[int, ...] = (20, 40, 80), compare_train_frames: int = 2000,
                  compare_eval_frames: int = 1000, seed: int = 0) -> list[Series]:
    """Log-log growth exponents (goal: at most linear, ``<= 1.15``).

    Series:

    - ``turbulence_vs_actuators``: seconds per frame streaming ``chunk_frames`` frames per timing in calls of
      ``stream_chunk`` (enough frames that every timing extends the strip by whole blocks, as a long run does);
    - ``turbulence_vs_frames``: seconds to stream ``turbulence_frames`` frames in ``stream_chunk``-frame calls (as
      ``run_loop`` does);
    - ``turbulence_vs_call_frames``: seconds of one ``frames(a, a + T)`` call on strip blocks already built (the
      same range every repeat), i.e. the interpolation alone, against ``T``;
    - ``step_vs_*`` / ``run_loop_vs_*``: controller step and ``run_loop`` per frame vs actuators and history length;
    - ``fit_vs_*``: streamed closed-form fit vs actuators, taps (open-loop history length) and frames;
    - ``compare_vs_actuators``: a whole comparison (integrator, open- and closed-loop EOF per actuator: training,
      closed-loop evaluation, stability analysis; ``eofnn compare`` without its files) at
      ``compare_across`` actuators across.

    ``x`` is the number of active actuators (not the number across), the history length, or the number of frames.
    One turbulence stream per grid serves every series (each timing continues it), so set-up costs are paid once.
    """
    out = []
    grids = {n: scenario_with_grid(scenario, n) for n in (*n_across, base_across)}
    streams = {n: ContinuingTurbulence(grids[n].turbulence(seed)) for n in grids}
    actuators = [grids[n].grid.n_actuators for n in n_across]
    base = grids[base_across]
    k_base = base.grid.n_actuators
    loop_spec = HistorySpec("closed_loop", loop_history, scenario.delay_frames)
    info = {"n_across": list(n_across)}

    out.append(Series("scaling", "turbulence_vs_actuators", "n_actuators", actuators,
                      [_turbulence_frame_s(streams[n], chunk_frames, stream_chunk, repeat) for n in n_across],
                      "s/frame", LINEAR, LINEAR_LABEL,
                      info=dict(info, frames=chunk_frames, frames_per_call=stream_chunk)))
    stream = streams[base_across]

    def stream_frames(n):
        for _ in range(0, n, stream_chunk):
            stream.take(stream_chunk)

    timings = time_interleaved({n: (lambda n=n: stream_frames(n), 1) for n in turbulence_frames}, repeat=repeat)
    out.append(Series("scaling", "turbulence_vs_frames", "frames", list(turbulence_frames),
                      [timings[n].min for n in turbulence_frames], "s/run", LINEAR, LINEAR_LABEL,
                      info={"n_across": base_across, "frames_per_call": stream_chunk}))
    first = stream.offset
    timings = time_interleaved({n: (lambda n=n: stream.turbulence.frames(first, first + n), 1) for n in call_frames},
                               repeat=repeat, warmup=1)
    stream.offset = first + max(call_frames)
    out.append(Series("scaling", "turbulence_vs_call_frames", "frames", list(call_frames),
                      [timings[n].min for n in call_frames], "s/call", LINEAR, LINEAR_LABEL,
                      info={"n_across": base_across, "note": "strip blocks already built: interpolation only"}))

    out.append(Series("scaling", "step_vs_actuators", "n_actuators", actuators,
                      [_step_s(k, loop_spec, steps, repeat, seed) for k in actuators], "s/step", LINEAR,
                      LINEAR_LABEL, info=dict(info, history_length=loop_history)))
    out.append(Series("scaling", "step_vs_history", "history_length", list(histories),
                      [_step_s(k_base, HistorySpec("closed_loop", p, scenario.delay_frames), steps, repeat, seed)
                       for p in histories], "s/step", LINEAR, LINEAR_LABEL, info={"n_across": base_across}))
    out.append(Series("scaling", "run_loop_vs_actuators", "n_actuators", actuators,
                      [_run_loop_s(grids[n], streams[n], loop_spec, loop_frames, repeat, seed) for n in n_across],
                      "s/frame",
                      LINEAR, LINEAR_LABEL, info=dict(info, history_length=loop_history)))
    out.append(Series("scaling", "run_loop_vs_history", "history_length", list(histories),
                      [_run_loop_s(base, streams[base_across], HistorySpec("closed_loop", p, scenario.delay_frames),
                                   loop_frames, repeat, seed) for p in histories], "s/frame", LINEAR, LINEAR_LABEL,
                      info={"n_across": base_across}))

    seconds = []
    for k in actuators:
        x, t = synthetic_regression(k, fit_actuator_frames, fit_taps, seed)
        seconds.append(_fit_s(x, t, batch_frames, repeat))
        del x, t
    out.append(Series("scaling", "fit_vs_actuators", "n_actuators", actuators, seconds, "s/fit", LINEAR,
                      LINEAR_LABEL, info=dict(info, frames=fit_actuator_frames, taps=fit_taps,
                                              batch_frames=batch_frames)))
    seconds = []
    for p in histories:
        x, t = synthetic_regression(k_base, fit_history_frames, p, seed)
        seconds.append(_fit_s(x, t, batch_frames, repeat))
        del x, t
    out.append(Series("scaling", "fit_vs_history", "taps", list(histories), seconds, "s/fit", LINEAR,
                      LINEAR_LABEL, info={"n_across": base_across, "frames": fit_history_frames,
                                          "batch_frames": batch_frames,
                                          "note": "D D^T costs taps**2 per sample: up to quadratic is expected"}))
    x, t = synthetic_regression(k_base, max(fit_frames), fit_taps, seed)
    seconds = [_fit_s(x[:, :n], t[:, :n], batch_frames, repeat) for n in fit_frames]
    del x, t
    out.append(Series("scaling", "fit_vs_frames", "frames", list(fit_frames), seconds, "s/fit", LINEAR,
                      LINEAR_LABEL, info={"n_across": base_across, "taps": fit_taps, "batch_frames": batch_frames}))
    if compare_across:
        compare_grids = [scenario_with_grid(scenario, n) for n in compare_across]
        out.append(Series("scaling", "compare_vs_actuators", "n_actuators",
                          [sc.grid.n_actuators for sc in compare_grids],
                          [_compare_s(sc, compare_train_frames, compare_eval_frames, repeat) for sc in compare_grids],
                          "s/run", LINEAR, LINEAR_LABEL,
                          info={"n_across": list(compare_across), "train_frames": compare_train_frames,
                                "eval_frames": compare_eval_frames, "predictors": sorted(COMPARE_PREDICTORS),
                                "what": "Experiment(...).run(): train, evaluate, analyse (eofnn compare without "
                                        "writing files)"}))
    return out


#: The end-to-end series' contenders: an integrator, open- and closed-loop EOF per actuator. (A neighbourhood
#: filter's coupled stability analysis grows much faster than linearly and is refused beyond 20000 companion rows,
#: 80 across among them: it would time that analysis, not the comparison; the ``coupled`` rows of the stability
#: benchmark time it.)
COMPARE_PREDICTORS = {
    "integrator": {"controller": "integrator", "gain": 0.4},
    "ol_eof": {"history_length": 4, "optimization": {"alpha": 1e-9}},
    "cl_eof": {"history": "closed_loop", "history_length": 5, "optimization": {"alpha": 1e-9}},
}


def _compare_s(scenario: Scenario, train_frames: int, eval_frames: int, repeat: int) -> float:
    """Seconds of a whole comparison (``eofnn compare``'s work, files aside) in ``scenario``."""
    from eofnn.evaluation.config import EvaluationConfig  # noqa: PLC0415 (only this series needs the experiment)
    from eofnn.evaluation.experiment import Experiment  # noqa: PLC0415

    data = {"frames": train_frames, "val_frames": max(100, train_frames // 5), "sequence_frames": train_frames}
    predictors = {name: dict(cfg, data=data) if "controller" not in cfg else cfg
                  for name, cfg in COMPARE_PREDICTORS.items()}
    evaluation = EvaluationConfig(frames=eval_frames, settle_frames=min(500, eval_frames // 4),
                                  psd_segment_frames=min(1024, eval_frames // 2))

    def run():
        Experiment(scenario, {"nominal": {}}, predictors, evaluation, progress=False, log=lambda _: None).run()

    return time_interleaved({"c": (run, 1)}, repeat=repeat, warmup=0)["c"].min
