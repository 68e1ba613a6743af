"""The contest through OOPAO's pyramid, as experiments/pyramid/README.md's tables ("The contest in OOPAO's loop").

Reads the committed summaries of ``bash experiments/interop/run.sh pyramid_contest``
(experiments/interop/pyramid_contest/m8 and m10/summary.json) and rates each predictor with the study's own report
code (:mod:`eofnn.studies.antialias_report`: ``gains``, ``etas``, ``best_in_contrast``): against the best classical
controller of the study (chosen on the scan realisation; PFC included), and against the best of those eofnn's loop
ran (integrator, modal integrator, LQG; eofnn's contest has no PFC), with the range over the paired realisations.

    python experiments/pyramid/oopao_contest.py
"""

from __future__ import annotations

import json
from pathlib import Path

from eofnn.studies.antialias_report import best_in_contrast, etas, gains

HERE = Path(__file__).resolve().parent.parent
EOFNN_LOOP = ("integrator", "modal", "lqg")  # the classical controllers eofnn's contest runs
SHOWN = ("integrator", "modal", "lqg", "pfc", "eof_measured", "eof_antialias", "oracle")


def load(magnitude: int) -> dict:
    return json.loads((HERE / "interop" / "pyramid_contest" / f"m{magnitude}" / "summary.json").read_text())["result"]


def rated(run: dict, against: str, classical: tuple[str, ...]) -> dict:
    """Each predictor against ``against``, the contrast against the one of ``classical`` best in contrast there."""
    left_out = {"integrator", "modal", "lqg", "pfc"} - set(classical)
    results = {n: r for n, r in run["contenders"].items() if n not in left_out}
    seps = tuple(run["config"]["separations_lod"])
    ratios = gains(results, run["fitting_error_nm"], seps, against, best_in_contrast(results, seps))
    shares = etas(results, against)
    out = {}
    for name in ("eof_measured", "eof_antialias", "oracle"):
        base, mine = (results[n]["realisations_median_rms_nm"] for n in (against, name))
        per = [b * b / (m * m) for b, m in zip(base, mine, strict=True)]
        out[name] = {**ratios[name], "variance_range": (min(per), max(per)), "eta": shares.get(name)}
    return out


def span(values) -> str:
    return f"{min(values):.2f}-{max(values):.2f}"


def table(magnitude: int) -> str:
    run = load(magnitude)
    c = run["contenders"]
    lines = [f"I = {magnitude} (identified gain {run['identified']['dm_gain']:.3f} = 2 x optical gain "
             f"{run['identified']['dm_gain'] / 2:.3f}; fitting error {span(run['fitting_error_nm'])} nm; best "
             f"classical on the scan realisation: {run['best_classical']}; integrator gain "
             f"{run['integrator_scan']['gain']})", "",
             "| contender | median RMS over the pupil, mean (range) nm | raw contrast at 3 λ/D |", "|---|---|---|"]
    for name in SHOWN:
        r = c[name]["realisations_median_rms_nm"]
        lines.append(f"| {name} | {c[name]['mean_of_realisations_nm']:.1f} ({min(r):.1f}-{max(r):.1f}) | "
                     f"{c[name]['mean_contrast']['3']:.2e} |")
    for against, classical, what in ((run["best_classical"], ("integrator", "modal", "lqg", "pfc"), "the study's best"),
                                     (min(EOFNN_LOOP, key=lambda n: c[n]["mean_of_realisations_nm"]), EOFNN_LOOP,
                                      "the best of eofnn's loop's classical controllers")):
        lines += ["", f"Against {against} ({what}):", "",
                  "| predictor | variance ratio (range) | RMS ratio | contrast ratio at 3 λ/D (against) | η (range) |",
                  "|---|---|---|---|---|"]
        for name, g in rated(run, against, classical).items():
            eta = g["eta"]
            eta_text = "1 (the bound)" if name == "oracle" else (
                f"{eta['eta']:.2f} ({span(eta['per_realisation'])})" if eta and eta["eta"] is not None else "")
            lines.append(f"| {name} | {g['variance']:.3f} ({span(g['variance_range'])}) | {g['rms']:.3f} | "
                         f"{g['contrast']['3']:.2f} ({g['contrast_against']['3']}) | {eta_text} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print("\n\n".join(table(m) for m in (8, 10) if (HERE / "interop" / "pyramid_contest" / f"m{m}").is_dir()))
