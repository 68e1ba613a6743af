"""Benchmark: the scheduling overhead of ``eofnn sweep`` against running the same compare runs in one process.

    .venv/bin/python -m benchmarks.bench_sweep                    # 100 tiny points, about 4 minutes on 2 cores
    .venv/bin/python -m benchmarks.bench_sweep --points 20 --workers 1,2 --out /tmp/sweep.json

Both contenders run the same ``n_points`` tiny points (8 actuators across, 300 frames, an uncorrected loop and an
integrator; each point still writes compare's three figures, which is most of its time), one torch thread each,
messages to a log file, every repeat into fresh folders:

- ``eofnn``: ``eofnn sweep`` end to end: grid checks, one resolved ``point.yaml`` per point, ``status.json``, the
  atomic rewrite of ``sweep.csv`` after every point, and the figures;
- baseline: a Python loop calling ``eofnn compare --config point.yaml`` on the same resolved configs (written
  before the clock starts), as the hand-written shell loop did without the process start-ups.

Row ``sweep/in_process/<n>`` (``--workers 1``, the sweep runs in this process) has the goal: overhead under 10%,
ratio ``>= 1/1.1``. Rows ``sweep/processes_<w>/<n>`` time ``w`` spawned worker processes against the same loop, for
information: they include each worker's start-up and import (seconds) and gain what free cores allow.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import tempfile
from pathlib import Path

import torch
import yaml

from benchmarks.common import Row, fmt_seconds, time_interleaved, time_once
from eofnn.cli.main import main as eofnn_main
from eofnn.cli.sweep import load_grid, plan

TINY_POINT = {
    "scenario": {"grid": {"diameter_m": 1.0, "n_across": 8},
                 "atmosphere": {"r0_m": 0.1, "r0_wavelength_m": 5.0e-7, "outer_scale_m": 20.0,
                                "layers": [{"cn2_fraction": 1.0, "wind_speed_mps": 10.0, "wind_direction_deg": 0.0}]}},
    "scenarios": {"nominal": {}},
    "predictors": {"uncorrected": {"controller": "uncorrected"}, "integrator": {"controller": "integrator"}},
    "evaluation": {"frames": 300, "settle_frames": 50, "psd_segment_frames": 64},
}


def tiny_grid(n_points: int) -> dict:
    """``n_points`` points: integrator gains (log-spaced) x evaluation seeds, at most 10 gains."""
    n_gains = min(10, n_points)
    if n_points % n_gains:
        raise ValueError(f"n_points={n_points} is invalid: it must be a multiple of 10 (or at most 10)")
    return {"predictors.integrator.gain": {"log_range": [0.05, 0.5, n_gains]} if n_gains > 1 else [0.3],
            "evaluation.seed": list(range(1, n_points // n_gains + 1))}


def bench_sweep(n_points: int = 100, workers: tuple[int, ...] = (1,), repeat: int = 1,
                warmup: int = 0) -> list[Row]:
    """Seconds per point of ``eofnn sweep`` against a loop of ``eofnn compare`` calls in one process."""
    torch.set_num_threads(1)  # what each sweep point uses (--threads 1), for the loop too
    rows = []
    with tempfile.TemporaryDirectory(prefix="eofnn-bench-sweep-") as tmp:
        tmp = Path(tmp)
        base, grid_path = tmp / "base.yaml", tmp / "grid.yaml"
        base.write_text(yaml.safe_dump(TINY_POINT))
        grid_path.write_text(yaml.safe_dump(tiny_grid(n_points)))
        configs = []
        plan_s, points = time_once(lambda: plan(base, load_grid(grid_path)))  # the sweep's own checks, timed alone
        for point in points:
            configs.append(tmp / "configs" / f"{point.id}.yaml")
            configs[-1].parent.mkdir(exist_ok=True)
            configs[-1].write_text(point.config_yaml)
        fresh = itertools.count()
        log = open(tmp / "log.txt", "w")

        def loop() -> None:
            run = tmp / f"loop_{next(fresh)}"
            for config in configs:
                code = eofnn_main(["compare", "--config", str(config), "--out", str(run / config.stem),
                                   "--progress", "false"])
                assert code == 0

        def sweep(n_workers: int) -> None:
            code = eofnn_main(["sweep", "--config", str(base), "--grid", str(grid_path), "--out",
                               str(tmp / f"sweep_{next(fresh)}"), "--workers", str(n_workers), "--progress", "false"])
            assert code == 0

        calls = {"loop": (loop, n_points)}
        for w in workers:
            calls[f"sweep/{w}"] = (lambda w=w: sweep(w), n_points)
        with log, contextlib.redirect_stderr(log):
            timings = time_interleaved(calls, repeat=repeat, warmup=warmup)
        for w in workers:
            in_process = w == 1
            rows.append(Row(
                "sweep", f"sweep/{'in_process' if in_process else f'processes_{w}'}/{n_points}", "s/point",
                timings[f"sweep/{w}"], timings["loop"], "the same compare runs in a loop, one process",
                goal_ratio=1 / 1.1 if in_process else None,
                goal_label=">= 0.91 (overhead < 10%)" if in_process else "",
                info={"n_points": n_points, "workers": w, "threads_per_point": 1, "plan_s": plan_s,
                      "overhead_fraction": timings[f"sweep/{w}"].min / timings["loop"].min - 1},
            ))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=100, help="Points of the sweep (a multiple of 10 above 10).")
    parser.add_argument("--workers", default="1", help="Comma-separated worker counts to time (1: in process).")
    parser.add_argument("--repeat", type=int, default=1, help="Timed rounds (each runs every contender once).")
    parser.add_argument("--out", type=Path, default=None, help="Write the rows as JSON here.")
    args = parser.parse_args(argv)
    rows = bench_sweep(args.points, tuple(int(w) for w in args.workers.split(",")), args.repeat)
    for row in rows:
        met = {None: "", True: "goal met", False: "goal MISSED"}[row.goal_met]
        print(f"{row.name}: sweep {fmt_seconds(row.eofnn.min)}/point, loop {fmt_seconds(row.baseline.min)}/point, "
              f"ratio {row.ratio:.3f} (overhead {row.info['overhead_fraction']:+.1%}; grid checks alone "
              f"{row.info['plan_s']:.2f} s) {row.goal_label} {met}")
    if args.out:
        args.out.write_text(json.dumps([row.to_dict() for row in rows], indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

