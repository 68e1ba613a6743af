"""The numbers of experiments/noise_aware/run.sh: closed-loop median RMS (pooled, and per realisation) of every
controller in evaluate_<N>nm, and each replay's prediction error, into one JSON file.

Usage: python experiments/noise_aware/summarise.py RUNS_DIR OUT_JSON
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def closed_loop(folder: Path) -> dict:
    metrics = json.loads((folder / "metrics.json").read_text())
    series = np.load(folder / "timeseries.npz")
    out = {}
    for scenario, controllers in metrics["scenarios"].items():
        for name, m in controllers.items():
            rms = np.asarray(series[f"{scenario}/{name}/rms_nm"])
            rms = rms.reshape(-1, rms.shape[-1])[:, m["settle_frames"]:]
            out.setdefault(scenario, {})[name] = {
                "median_rms_nm": m["median_rms_nm"], "diverged": m["diverged"],
                "realisation_median_rms_nm": [float(v) for v in np.median(rms, axis=1)]}
        gains = metrics.get("integrator_gain_used") or {}
        if scenario in gains:
            out[scenario]["integrator"]["gain"] = gains[scenario]
    return out


def main(runs: Path, out: Path) -> None:
    summary = {"closed_loop": {}, "replay": {}}
    for folder in sorted(runs.glob("evaluate_*nm")):
        summary["closed_loop"].update(closed_loop(folder))
    for folder in sorted((runs / "replay").glob("*_on_*nm")):
        replay = json.loads((folder / "replay.json").read_text())
        summary["replay"][folder.name] = {
            "predictor_nm": replay["predictor"]["median_rms_noise_corrected_nm"],
            "own_controller_nm": replay["own_controller"]["median_rms_noise_corrected_nm"],
            "identified_noise_nm": replay["noise_nm"], "shift": replay["shift"]}
    out.write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
