"""Benchmark: how fast the command line answers ``--help`` and a config error, against a bare Python start-up.

    .venv/bin/python -m benchmarks.bench_startup                  # 7 repeats, about 10 s on 2 cores
    .venv/bin/python -m benchmarks.bench_startup --repeat 15

Each timing is one fresh process, start to exit, the way a user meets the command line:

- ``eofnn``: ``python -m eofnn.cli.main compare --help``, and ``compare --config TYPO.yaml`` whose YAML has an unknown
  key (exit code 2, one line), and ``compare --config realistic_small.yaml --evaluation.frames -5`` (a value out of
  range, exit code 2, one line);
- baseline: ``python -c pass`` (the interpreter's own start-up), timed alternately with them.

Rows ``startup/help``, ``startup/unknown_key`` and ``startup/out_of_range``: ratio = ``python -c pass`` / eofnn (higher
is better; 1 would be an answer as fast as an empty interpreter). Goal: ratio >= 0.025, within 40 bare start-ups
(about a second where a bare start-up takes 25 ms), which holds only while the answer comes before torch, Lightning,
HCIPy, scipy and matplotlib are imported: their import alone is some 200 bare start-ups (ratio 0.004-0.0045 before
they were deferred). ``info.heavy_imported`` says, for each command, which of those the process
had imported when it answered (``tests/test_help_speed.py`` asserts none).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import Row, Timing, fmt_seconds

ROOT = Path(__file__).resolve().parent.parent
HEAVY = ("torch", "lightning", "hcipy", "scipy", "matplotlib")
#: Runs the command line as ``eofnn`` does and prints, last, which heavy libraries it had imported when it answered.
PROBE = f"""
import json, sys
from eofnn.cli.main import main
try:
    code = main(sys.argv[1:])
except SystemExit as stop:
    code = stop.code
print(json.dumps({{"code": code, "heavy": [m for m in {HEAVY!r} if m in sys.modules]}}))
"""
GOAL_RATIO = 0.025


def _command_lines(folder: Path) -> dict[str, list[str]]:
    """Row name -> the arguments after ``eofnn``."""
    typo = folder / "typo.yaml"
    typo.write_text("scenario: realistic.yaml\nevaluation: {frames: 1000, setle_frames: 100}\n")
    return {
        "help": ["compare", "--help"],
        "unknown_key": ["compare", "--config", str(typo), "--out", str(folder / "out")],
        "out_of_range": ["compare", "--config", str(ROOT / "configs" / "realistic_small.yaml"), "--evaluation.frames",
                         "-5", "--out", str(folder / "out")],
    }


def _timed_run(argv: list[str]) -> tuple[float, subprocess.CompletedProcess]:
    """Wall seconds of one fresh process running ``argv``, and its result."""
    t0 = time.perf_counter()
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=300)
    return time.perf_counter() - t0, proc


def bench_startup(repeat: int = 7, warmup: int = 1) -> list[Row]:
    """One row per command line: seconds to its answer against ``python -c pass``, alternately, fresh processes."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="eofnn-bench-startup-") as tmp:
        for name, args in _command_lines(Path(tmp)).items():
            eofnn_argv = [sys.executable, "-c", PROBE, *args]
            bare_argv = [sys.executable, "-c", "pass"]
            eofnn_s, bare_s, answers = [], [], []
            for r in range(warmup + repeat):  # alternate, so that background load hits both alike
                t_bare, _ = _timed_run(bare_argv)
                t_eofnn, proc = _timed_run(eofnn_argv)
                answers.append(json.loads(proc.stdout.strip().splitlines()[-1]))
                if r >= warmup:
                    bare_s.append(t_bare)
                    eofnn_s.append(t_eofnn)
            codes = sorted({a["code"] for a in answers})
            heavy = sorted({m for a in answers for m in a["heavy"]})
            if codes != ([0] if name == "help" else [2]):
                raise RuntimeError(f"eofnn {' '.join(args)} answered with exit code(s) {codes}")
            rows.append(Row("startup", f"startup/{name}", "s per answer", Timing(eofnn_s), Timing(bare_s),
                            "python -c pass", GOAL_RATIO, f"ratio >= {GOAL_RATIO} (within 40 bare start-ups)",
                            info={"command": "eofnn " + " ".join(args[:2]) + (" ..." if len(args) > 2 else ""),
                                  "exit_code": codes[0], "heavy_imported": heavy}))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_startup", description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7, help="timed runs of each command (and of python -c pass)")
    args = parser.parse_args(argv)
    for row in bench_startup(args.repeat):
        print(f"{row.name:22s} eofnn {fmt_seconds(row.eofnn.min)} (median {fmt_seconds(row.eofnn.median)}), "
              f"python -c pass {fmt_seconds(row.baseline.min)}: ratio {row.ratio:.3g} (median {row.ratio_median:.3g})"
              f", heavy imported: {row.info['heavy_imported'] or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
