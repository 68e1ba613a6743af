"""The anti-aliasing EOF trained in a twin identified from OOPAO's telemetry alone, carried into OOPAO's 40 x 40 loop
(experiments/interop/twin_identified/run.sh full; summaries written by its gap.py)."""

from __future__ import annotations

import json

from report_common import HERE
from report_oopao import _summed as _variance  # median RMS squared summed over the realisations

COMMAND = "bash experiments/interop/twin_identified/run.sh full"
#: The run the page and the findings read; the same command on earlier code is kept beside it.
RUN = "interop/twin_identified/m8_2layers"
BEFORE = "interop/twin_identified/m8_2layers_before_r0fix"
NAMES = {"pfc": "PFC", "integrator": "integrator", "modal": "modal integrator", "lqg": "LQG"}


def twin_identified_numbers(summary: dict) -> dict:
    """The gap closed (plain variance), each contender's mean residual and the ratios over the best classical."""
    gap = summary["gap_closed"]["eof_twin_identified"]
    best = gap["on_scored"]["best_classical"]
    runs = summary["residual_nm_per_realisation"]
    ratio = {name: _variance(runs[best]) / _variance(runs[name]) for name in ("eof_twin_identified", "eof_antialias",
                                                                          "eof_measured") if name in runs}
    measured = (_variance(runs[best]) - _variance(runs["eof_measured"])) / (
        _variance(runs[best]) - _variance(runs["eof_antialias"]))
    return {"share": gap["on_scored"]["share"], "best": best, "ratio": ratio, "measured_share": measured,
            "mean_nm": {k: sum(v) / len(v) for k, v in runs.items()}, "identified": summary["identified_twin"],
            "seeds": summary["scored_seeds"]}


def twin_identified_row() -> dict | None:
    summary = json_summary(RUN)
    if not summary:
        return None
    n = twin_identified_numbers(summary)
    return {"section": "2d",
            "claim": "An anti-aliasing EOF trained in a twin identified from OOPAO's telemetry alone (no setting or "
                     "truth of OOPAO read) and carried into OOPAO's loop closes most of the gap between the strongest "
                     "classical controller and the same filter trained on OOPAO's truth",
            "number": f"{100 * n['share']:.0f}% of the gap in plain variance; over the {NAMES[n['best']]} "
                      f"{n['ratio']['eof_twin_identified']:.2f}x (the truth-trained filter "
                      f"{n['ratio']['eof_antialias']:.2f}x, the EOF fitted on the telemetry "
                      f"{n['ratio']['eof_measured']:.2f}x)",
            "conditions": "OOPAO's 8 m, 40 x 40 Shack-Hartmann, I = 8, two layers (70% at 20 m/s, 30% at 10 m/s, OOPAO's "
                          f"30° and 120°); scored realisations {', '.join(map(str, n['seeds']))} fixed in run.sh before "
                          "the run, 800 scored frames each"}


def json_summary(name: str) -> dict | None:
    """The whole summary.json of ``name`` (gap.py writes it unwrapped)."""
    file = HERE / name / "summary.json"
    return json.loads(file.read_text()) if file.is_file() else None


def twin_identified_text() -> str:
    summary = json_summary(RUN)
    if not summary:
        return f"**Trained in a twin identified from the telemetry** (`{COMMAND}`): not run."
    n = twin_identified_numbers(summary)
    ident = n["identified"]
    layers = ", ".join(f"{lay['speed_mps']:.2f} m/s at {lay['direction_deg']:.1f}° ({lay['weight']:.2f})"
                       for lay in ident["layers"])
    means = ", ".join(f"{k} {v:.1f}" for k, v in n["mean_nm"].items())
    before = json_summary(BEFORE)
    earlier = "" if not before else (
        f" The same command on the code before the twin's references were projected on the record's modes (its r0 "
        f"{before['identified_twin']['r0_m']:.3f} m) closed {100 * twin_identified_numbers(before)['share']:.1f}%.")
    return (f"**Trained in a twin identified from the telemetry** (`{COMMAND}`; `--twin-identified`, "
            "`eofnn/studies/twin_transfer.py`): OOPAO's dithered integrator is recorded through a view with only what a "
            "real-time computer has, `eofnn twin`'s identification runs on that record alone, and the anti-aliasing "
            "EOF is trained in the identified twin and carried into OOPAO's loop. At 40 x 40, I = 8, two layers (70% "
            "at 20 m/s, OOPAO's 30°; 30% at 10 m/s, 120°) the twin found " + layers + f" (eofnn's directions), r0 "
            f"{ident['r0_m']:.3f} m (OOPAO's 0.15), L0 {ident['outer_scale_m']:g} m (OOPAO's 25). Mean residual over "
            f"the scored realisations {', '.join(map(str, n['seeds']))} (nm): {means}. Against the strongest classical "
            f"controller ({NAMES[n['best']]}), the twin-trained filter closes **{100 * n['share']:.1f}%** of the gap "
            f"to the truth-trained one in plain variance (goal 80%); the 5 x 5 EOF fitted on the telemetry alone "
            f"closes {100 * n['measured_share']:.1f}%: most of the gap is what any predictor fitted to this loop "
            "gains, and the twin's anti-aliasing adds the rest." + earlier)
