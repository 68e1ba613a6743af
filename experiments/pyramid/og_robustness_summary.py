"""Summarise the two runs of experiments/pyramid/og_robustness.yaml (without and with the optical gains compensated):
per contender its median residual over the pupil before the r0 change (settled frames to the change) and after it
(from 50 ms after the ramp's end), its 95th percentile, and the optical gains the runs report.

    python experiments/pyramid/og_robustness_summary.py experiments/runs/pyramid/og_off experiments/runs/pyramid/og_on \
        --out experiments/pyramid/og_robustness/summary.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

SCENARIO = "r0_drop"


def summarise(run: Path) -> dict:
    metrics = json.loads((run / "metrics.json").read_text())
    config = metrics["scenarios"][SCENARIO]
    series = np.load(run / "timeseries.npz")
    settle = next(iter(config.values()))["settle_frames"]
    out = {"integrator_gain": metrics["integrator_gains"][SCENARIO]["integrator"]["gain"]}
    for name, m in config.items():
        rms = series[f"{SCENARIO}/{name}/rms_nm"]
        change = m["reconvergence"][0] if m.get("reconvergence") else None
        entry = {"diverged_frame": m["diverged_frame"]}
        if not m["diverged"] and change is not None:
            start = round((change["end_s"] - 0.05) * 1000.0)  # the change's start (1 kHz, 50 ms ramp)
            after = round((change["end_s"] + 0.05) * 1000.0)
            entry.update(median_nm=float(np.median(rms[settle:])), before_nm=float(np.median(rms[settle:start])),
                         after_nm=float(np.median(rms[after:])), p95_nm=float(np.percentile(rms[settle:], 95)))
        gains = m.get("optical_gains")
        if gains:
            entry["optical_gains"] = {k: gains[k] for k in ("low_order_mean", "high_order_mean",
                                                            "effective_low_order_mean", "effective_high_order_mean")
                                      if k in gains}
            if "compensation" in gains:
                entry["optical_gains"]["calibrated_mean"] = gains["compensation"]["mean_gain"]
                entry["optical_gains"]["calibration_residual_rms_nm"] = gains["compensation"]["residual_rms_nm"]
        out[name] = entry
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    summary = {run.name: summarise(run) for run in args.runs}
    args.out.write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
