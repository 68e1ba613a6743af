"""Benchmark: the flagship Shack-Hartmann job against the zonal main job, each a fresh ``eofnn compare`` process.

    .venv/bin/python -m benchmarks.bench_flagship                 # one run of each, about 2-3 minutes on 2 idle cores
    .venv/bin/python -m benchmarks.bench_flagship --repeat 2

Row ``flagship/compare``: wall seconds of ``eofnn compare --config configs/flagship_sh.yaml`` (extreme AO through a
40 x 40 Shack-Hartmann: the tuned classical set, the anti-aliasing EOF and the guarded EOF, with the error budget and
contrast) against ``eofnn compare --config configs/realistic_small.yaml`` (the zonal main job), run alternately so
that background load hits both alike. Ratio = realistic_small / flagship (higher is better). Goal: ratio >= 1 / 1.7
(the flagship within 1.7x the zonal job); ``info`` adds each job's CPU seconds (user + system of the process and its
children), peak memory, and whether the flagship took at most 90 s of wall time (``within_90_s``). ``--quick`` times
the tiny variants instead (``tests/conf/flagship_tiny.yaml`` against ``tests/conf/tiny_compare.yaml``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks.common import Row, Timing, alternate_compares, fmt_seconds

ROOT = Path(__file__).resolve().parent.parent
#: ``(flagship, baseline)`` configs of the full run and of ``--quick``.
CONFIGS = {False: (ROOT / "configs" / "flagship_sh.yaml", ROOT / "configs" / "realistic_small.yaml"),
           True: (ROOT / "tests" / "conf" / "flagship_tiny.yaml", ROOT / "tests" / "conf" / "tiny_compare.yaml")}
GOAL_RATIO = 1 / 1.7
WALL_GOAL_S = 90.0


def bench_flagship(repeat: int = 1, quick: bool = False) -> list[Row]:
    """One row: the flagship's wall time against the zonal main job's, alternately, fresh processes."""
    flagship, baseline = CONFIGS[quick]
    times = alternate_compares({"baseline": (baseline, ()), "flagship": (flagship, ())}, repeat)
    wall = {k: [t[0] for t in v] for k, v in times.items()}
    info = {"flagship_config": str(flagship.relative_to(ROOT)), "baseline_config": str(baseline.relative_to(ROOT)),
            "flagship_cpu_s": [t[1] for t in times["flagship"]], "baseline_cpu_s": [t[1] for t in times["baseline"]],
            "peak_rss_mb_max": max(t[2] for v in times.values() for t in v),
            "flagship_wall_goal_s": WALL_GOAL_S, "within_90_s": min(wall["flagship"]) <= WALL_GOAL_S}
    return [Row("flagship", "flagship/compare", "s per job", Timing(wall["flagship"]), Timing(wall["baseline"]),
                f"eofnn compare --config {baseline.relative_to(ROOT)}", GOAL_RATIO,
                "ratio >= 1/1.7 (the flagship within 1.7x the zonal main job)", info=info)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_flagship", description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=1, help="timed runs of each job, alternately")
    parser.add_argument("--quick", action="store_true", help="the tiny variants (seconds)")
    args = parser.parse_args(argv)
    for row in bench_flagship(args.repeat, args.quick):
        print(f"{row.name}: flagship {fmt_seconds(row.eofnn.min)} (CPU {min(row.info['flagship_cpu_s']):.1f} s), "
              f"{row.baseline_label} {fmt_seconds(row.baseline.min)} (CPU {min(row.info['baseline_cpu_s']):.1f} s): "
              f"ratio {row.ratio:.3g} (goal >= {GOAL_RATIO:.3g}); within 90 s: {row.info['within_90_s']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
