"""Benchmark: the pyramid's realistic job against its Shack-Hartmann twin, each a fresh ``eofnn compare`` process.

    .venv/bin/python -m benchmarks.bench_pyramid                 # one run of each, minutes on 2 cores
    .venv/bin/python -m benchmarks.bench_pyramid --repeat 2

Row ``pyramid/compare``: wall seconds of ``eofnn compare --config configs/realistic_pyr.yaml`` (the flagship's sky
through eofnn's modulated pyramid on 20 x 20 actuators: the best-gain integrator, with the optical gains measured on
its residual, the LQG and the neighbourhood EOF) against the same command with ``--scenario.sensor.kind
shack_hartmann --scenario.sensor.samples_per_subaperture 2`` (the same telescope, sky and contenders through the
flagship's Shack-Hartmann), run alternately so that background load hits both alike. Ratio = Shack-Hartmann /
pyramid (higher is better). Goal: ratio >= 1/3 (the pyramid within 3x its Shack-Hartmann twin); ``info`` adds each
job's CPU seconds (user + system of the process and its children) and the peak memory. ``--quick`` times the tiny
variant (``tests/conf/pyr_tiny.yaml``) and its twin.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks.common import Row, Timing, alternate_compares, fmt_seconds

ROOT = Path(__file__).resolve().parent.parent
#: The pyramid's config of the full run and of ``--quick``; the Shack-Hartmann twin is the same with ``TWIN``.
CONFIGS = {False: ROOT / "configs" / "realistic_pyr.yaml", True: ROOT / "tests" / "conf" / "pyr_tiny.yaml"}
TWIN = ("--scenario.sensor.kind", "shack_hartmann", "--scenario.sensor.samples_per_subaperture", "2")
GOAL_RATIO = 1 / 3


def bench_pyramid(repeat: int = 1, quick: bool = False) -> list[Row]:
    """One row: the pyramid job's wall time against its Shack-Hartmann twin's, alternately, fresh processes."""
    config = CONFIGS[quick]
    times = alternate_compares({"twin": (config, TWIN), "pyramid": (config, ())}, repeat)
    wall = {k: [t[0] for t in v] for k, v in times.items()}
    cpu = {k: [t[1] for t in v] for k, v in times.items()}
    info = {"config": str(config.relative_to(ROOT)), "twin_overrides": " ".join(TWIN),
            "pyramid_cpu_s": cpu["pyramid"], "twin_cpu_s": cpu["twin"],
            "cpu_ratio": min(cpu["twin"]) / min(cpu["pyramid"]),
            "peak_rss_mb_max": max(t[2] for v in times.values() for t in v)}
    return [Row("pyramid", "pyramid/compare", "s per job", Timing(wall["pyramid"]), Timing(wall["twin"]),
                f"eofnn compare --config {config.relative_to(ROOT)} {' '.join(TWIN)}", GOAL_RATIO,
                "ratio >= 1/3 (the pyramid within 3x its Shack-Hartmann twin)", info=info)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_pyramid", description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=1, help="timed runs of each job, alternately")
    parser.add_argument("--quick", action="store_true", help="the tiny variant (seconds)")
    args = parser.parse_args(argv)
    for row in bench_pyramid(args.repeat, args.quick):
        print(f"{row.name}: pyramid {fmt_seconds(row.eofnn.min)} (CPU {min(row.info['pyramid_cpu_s']):.1f} s), "
              f"Shack-Hartmann twin {fmt_seconds(row.baseline.min)} (CPU {min(row.info['twin_cpu_s']):.1f} s): "
              f"ratio {row.ratio:.3g} in wall time, {row.info['cpu_ratio']:.3g} in CPU (goal >= {GOAL_RATIO:.3g})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
