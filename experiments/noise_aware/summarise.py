"""The numbers of experiments/noise_aware/run.sh: closed-loop median RMS of every controller in evaluate_* (frames
of its 3 realisations pooled; results.md beside them gives the spread of the best rows), and each replay's
noise-corrected prediction error, into one JSON file, and the README's table on stdout.

Usage: python experiments/noise_aware/summarise.py RUNS_DIR OUT_JSON
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def closed_loop(folder: Path, out: dict) -> None:
    """``out[scenario][controller]``: the closed-loop numbers of one evaluate folder."""
    metrics = json.loads((folder / "metrics.json").read_text())
    for scenario, controllers in metrics["scenarios"].items():
        for name, m in controllers.items():
            out.setdefault(scenario, {})[name] = {"median_rms_nm": m["median_rms_nm"], "diverged": m["diverged"]}


def main(runs: Path, out: Path) -> None:
    summary = {"closed_loop": {}, "replay": {}}
    for folder in sorted(runs.glob("evaluate_*")):
        closed_loop(folder, summary["closed_loop"])
    for folder in sorted((runs / "replay").glob("*_on_*nm")):
        replay = json.loads((folder / "replay.json").read_text())
        summary["replay"][folder.name] = {
            "predictor_nm": replay["predictor"]["median_rms_noise_corrected_nm"],
            "own_controller_nm": replay["own_controller"]["median_rms_noise_corrected_nm"],
            "identified_noise_nm": replay["noise_nm"], "shift": replay["shift"]}
    out.write_text(json.dumps(summary, indent=1) + "\n")
    print(table(summary))


def table(summary: dict) -> str:
    """The README's table: per controller and noise level, closed-loop median RMS (pooled; per realisation) and the
    replay's noise-corrected prediction error on held-out telemetry of that noise."""
    lines = ["| controller | WFS noise (nm) | closed loop: median RMS (nm) | replay (nm) |", "|---|---|---|---|"]
    for scenario, controllers in summary["closed_loop"].items():
        noise = scenario.removeprefix("noise_")
        for name, m in controllers.items():
            rms = "diverged" if m["diverged"] else f"{m['median_rms_nm']:.2f}"
            replay = summary["replay"].get(f"{name}_on_{noise}nm", {}).get("predictor_nm")
            lines.append(f"| {name} | {noise} | {rms} | {'' if replay is None else f'{replay:.2f}'} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
