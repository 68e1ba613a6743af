"""The analytic DM-gain interval of a neighbourhood (coupled) filter against simulated bisection, with their times.

    .venv/bin/python experiments/coupled_margins.py --out experiments/runs/coupled_margins/realistic_10.json

fits an open-loop neighbourhood EOF (radius 1.5 pitches, ``--history`` taps, simulator truth, ``--frames`` training
and ``--val_frames`` validation frames, ``alpha: auto``) in ``--scenario`` (configs/realistic.yaml: 40 across, 1264
actuators), then times its coupled analysis (:func:`eofnn.analysis.stability.analyse_filter`: pole, DM-gain
interval, delay margins) and the closed-loop bisection of ``eofnn compare --simulated_margins``
(:func:`eofnn.evaluation.margins.simulated_dm_gain_interval`: ``--eval_frames`` frames per probe, ``--settle_frames``
settled, bounds within ``--tolerance``), and writes both as JSON with their wall-clock and CPU seconds (the CPU
seconds of all threads: on a shared machine the wall clock mostly measures the others).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def measure(scenario_path: Path, history: int, frames: int, val_frames: int, eval_frames: int, settle_frames: int,
            tolerance: float, seed: int) -> dict:
    from eofnn.analysis.block import companion_rows
    from eofnn.analysis.linear import controller_stability
    from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
    from eofnn.evaluation.experiment import Experiment
    from eofnn.evaluation.margins import simulated_dm_gain_interval
    from eofnn.sim.scenario import Scenario

    scenario = Scenario.from_yaml(scenario_path)
    name = f"ol_eof_nb{history}"
    predictor = PredictorConfig(
        history="open_loop", history_length=history,
        network={"class_path": "eofnn.models.linear.LinearFilter",
                 "init_args": {"structure": "neighbourhood", "radius": 1.5}},
        data={"frames": frames, "val_frames": val_frames, "sequence_frames": frames})
    evaluation = EvaluationConfig(frames=eval_frames, settle_frames=settle_frames, seed=seed)
    experiment = Experiment(scenario, {"nominal": {}}, {name: predictor}, evaluation)
    start = time.perf_counter()
    trained = experiment.predictor(name, "nominal")
    fit_seconds = time.perf_counter() - start
    start, cpu = time.perf_counter(), time.process_time()
    analytic = controller_stability(experiment.config(name, "nominal"), trained, experiment.scenarios["nominal"])
    analysis_seconds, analysis_cpu = time.perf_counter() - start, time.process_time() - cpu
    start, cpu = time.perf_counter(), time.process_time()
    simulated = simulated_dm_gain_interval(experiment, name, "nominal", tolerance)
    simulation_seconds, simulation_cpu = time.perf_counter() - start, time.process_time() - cpu
    low, high = analytic.gain_margin
    sim_low, sim_high = simulated["dm_gain_interval"]
    return {
        "scenario": str(scenario_path), "n_actuators": scenario.grid.n_actuators, "history_length": history,
        "companion_rows": companion_rows(scenario.grid.n_actuators, "open_loop", history,
                                         scenario.plant.delay_frames, scenario.plant.delay_frames),
        "alpha": trained.info.get("alpha_choice", {}).get("alpha"), "fit_seconds": round(fit_seconds, 1),
        "analytic": {"dm_gain_interval": [low, high], "max_root_modulus": float(analytic.max_root_modulus.max()),
                     "delay_margin_frames": float(analytic.delay_margin_frames.min()),
                     "seconds": round(analysis_seconds, 1), "cpu_seconds": round(analysis_cpu, 1)},
        "simulated": {**simulated, "seconds": round(simulation_seconds, 1), "cpu_seconds": round(simulation_cpu, 1),
                      "eval_frames": eval_frames,
                      "settle_frames": settle_frames},
        "difference": [abs(low - sim_low), None if sim_high is None else abs(high - sim_high)],
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", type=Path, default=ROOT / "configs" / "realistic.yaml")
    parser.add_argument("--history", type=int, default=10)
    parser.add_argument("--frames", type=int, default=4000)
    parser.add_argument("--val_frames", type=int, default=1000)
    parser.add_argument("--eval_frames", type=int, default=2000)
    parser.add_argument("--settle_frames", type=int, default=500)
    parser.add_argument("--tolerance", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    out = measure(args.scenario, args.history, args.frames, args.val_frames, args.eval_frames, args.settle_frames,
                  args.tolerance, args.seed)
    text = json.dumps(out, indent=1)
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return out


if __name__ == "__main__":
    main()
