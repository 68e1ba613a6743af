"""The 40 x 40 points of `run.sh oopao_aa` (OOPAO's 8 m, 40 x 40 loop, 20 m/s, DM applying 2x; I = 8 is m8, I = 10
m10) as the scripts that revisit them rebuild them: the run's integrator gain and scored seeds, the loop, and the
anti-aliasing study's frames."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from eofnn.interop.oopao import OopaoLoop
from eofnn.studies.antialias import AntiAliasConfig

RUNS = Path(__file__).resolve().parents[1] / "runs" / "interop"


def aa_point(magnitude: int) -> tuple[float, list[int], OopaoLoop, AntiAliasConfig]:
    """``(integrator gain scanned by the run, its scored seeds, the loop, the study's config)`` of the point at guide
    star magnitude ``magnitude`` (8 or 10) from its run (or the page's committed summary of it), or exit in one line
    if both are missing."""
    if magnitude not in (8, 10):
        sys.exit(f"magnitude {magnitude!r} is not a 40 x 40 point of `run.sh oopao_aa`: 8 or 10")
    name = f"m{magnitude}"
    page = RUNS / "oopao_aa" / name / "metrics.json"
    committed = Path(__file__).resolve().parent / "oopao_aa" / name / "summary.json"  # the page's copy of that run
    if page.is_file():
        run = json.loads(page.read_text())
    elif committed.is_file():
        run = json.loads(committed.read_text())["result"]
    else:
        sys.exit(f"{page} is missing: run the {name} point of `bash experiments/interop/run.sh oopao_aa` first")
    sim = OopaoLoop(40, 8.0, photon_noise=True, magnitude=float(magnitude), dm_gain=2.0, wind_speed_mps=20.0,
                    rcond=0.075)
    config = AntiAliasConfig(train_frames=2000, val_frames=400, loop_frames=1000, settle_frames=200, warmup_frames=100)
    return float(run["integrator_scan"]["gain"]), run["scored_seeds"], sim, config


def m8_point() -> tuple[float, list[int], OopaoLoop, AntiAliasConfig]:
    """:func:`aa_point` at I = 8."""
    return aa_point(8)
