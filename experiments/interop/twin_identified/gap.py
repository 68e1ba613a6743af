"""The share of the gap closed by the twin-trained EOFs of the runs of run.sh (eofnn.studies.twin_transfer.gap_closed),
recomputed from each run's metrics.json: writes experiments/interop/twin_identified/<run>/{summary.json,results.md}.

    python experiments/interop/twin_identified/gap.py small_m8_2layers m8_2layers
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from eofnn.studies.twin_transfer import gap_closed

RUNS = Path("experiments/runs/interop/twin_identified")
HERE = Path(__file__).resolve().parent


def main(names: list[str]) -> None:
    for name in names:
        metrics = json.loads((RUNS / name / "metrics.json").read_text())
        gaps = {p: gap_closed(metrics, p) for p in ("eof_twin_identified", "eof_eofnn") if p in metrics["contenders"]}
        contenders = {k: v["realisations_median_rms_nm"] for k, v in metrics["contenders"].items()}
        summary = {"command": metrics["command"], "scored_seeds": metrics["scored_seeds"],
                   "residual_nm_per_realisation": contenders, "gap_closed": gaps,
                   "identified_twin": metrics["fits"]["eof_twin_identified"].get("identified"),
                   "knowledge": {"eof_twin_identified": metrics["fits"]["eof_twin_identified"].get("knowledge"),
                                 "eof_eofnn": "OOPAO's settings (r0, L0, each layer's wind): simulator knowledge, a "
                                              "reference row"},
                   "seconds": metrics.get("seconds")}
        out = HERE / name
        out.mkdir(exist_ok=True)
        (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
        shutil.copy(RUNS / name / "results.md", out / "results.md")
        for predictor, gap in gaps.items():
            print(name, predictor, {k: gap[k] for k in ("on_scan", "on_scored")})


if __name__ == "__main__":
    main(sys.argv[1:] or ["small_m8_2layers", "m8_2layers"])
