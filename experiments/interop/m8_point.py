"""The m8 point of `run.sh oopao_aa` (OOPAO's 8 m, 40 x 40 loop, I = 8, 20 m/s, DM applying 2x) as the scripts that
revisit it rebuild it: its run's integrator gain and scored seeds, the loop, and the anti-aliasing study's frames."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from eofnn.interop.antialias import AntiAliasConfig
from eofnn.interop.oopao import OopaoLoop

RUNS = Path(__file__).resolve().parents[1] / "runs" / "interop"


def m8_point() -> tuple[float, list[int], OopaoLoop, AntiAliasConfig]:
    """``(integrator gain scanned by the run, its scored seeds, the loop, the study's config)``, or exit in one line
    if the run is missing."""
    page = RUNS / "oopao_aa" / "m8" / "metrics.json"
    if not page.is_file():
        sys.exit(f"{page} is missing: run the m8 point of `bash experiments/interop/run.sh oopao_aa` first")
    run = json.loads(page.read_text())
    sim = OopaoLoop(40, 8.0, photon_noise=True, magnitude=8.0, dm_gain=2.0, wind_speed_mps=20.0, rcond=0.075)
    config = AntiAliasConfig(train_frames=2000, val_frames=400, loop_frames=1000, settle_frames=200, warmup_frames=100)
    return float(run["integrator_scan"]["gain"]), run["scored_seeds"], sim, config
