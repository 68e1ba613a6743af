"""The findings table that opens experiments/README.md (and that the project's README copies): one row per finding,
each computed from the committed summaries like the rest of the page.

Every row gives the plain variance ratio first (the comparison's RMS squared: a controller's residual variance over
the predictor's, above 1 the predictor wins), then, labelled, any ratio after the fitting error is removed, or in
contrast. A summary that is missing drops its row, said in the table.
"""

from __future__ import annotations

import math
import re

from report_common import load, rms
from report_sh import STRUCTURE, structure_rows
from report_twin_identified import twin_identified_row
from report_where import rows as where_rows

#: The page's sections the rows link to, by their titles (the anchors are computed as GitHub computes them).
SECTIONS = {
    "1": "1. The study's Figure 3, on the study's own turbulence",
    "2b": "2b. Through a real sensor: the main job's twin on a Shack-Hartmann",
    "2d": "2d. Where prediction pays through a real sensor",
}


def anchor(title: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", title.lower()).replace(" ", "-")


def _x(value: float) -> str:
    """A ratio with three significant digits, at least two decimals below 10 (1.02x, 15.0x, 298x)."""
    if value is None or math.isnan(value):
        return "n/a"
    return f"{value:.2f}x" if value < 10 else f"{value:.1f}x" if value < 100 else f"{value:.0f}x"


def _span(values: list[float]) -> str:
    values = [v for v in values if not math.isnan(v)]
    if not values:
        return "n/a"
    low, high = f"{min(values):.2f}x", f"{max(values):.2f}x"
    return low if low == high else f"{low}-{high}"


def _best(scenario: dict, names: tuple[str, ...]) -> str | None:
    held = [n for n in names if not math.isnan(rms(scenario.get(n)))]
    return min(held, key=lambda n: rms(scenario[n])) if held else None


#: How the rows name eofnn's controllers.
NAMES = {"integrator": "the best-gain integrator", "lqg": "the LQG (model and noise scale tuned)",
         "modal_integrator": "the modal integrator (per-mode gains, margin tuned)"}


def flagship_row() -> dict | None:
    result = load("flagship")
    if result is None:
        return None
    verdict = result["verdict"]["scenarios"]["nominal"]
    ratios, best = verdict["ratios"], verdict["best_predictor"]["name"]
    mine = ratios["predictors"][best]
    spread = mine["variance_ratio_spread"]["per_realisation"]
    contrast = mine["raw_contrast"]["3"]
    guard = (result.get("fallback") or {}).get("nominal", {})
    deployed = [g for g in guard.values() if g.get("deployed") in ("predictor", "composite")]
    guarded = "" if not deployed else ("whole" if deployed[0]["deployed"] == "predictor" else
                                       f"on {deployed[0]['predictor_modes']} of {deployed[0]['n_modes']} KL modes")
    classical = [n for n in result["scenarios"]["nominal"] if n not in ratios["predictors"]]
    scored = result["scenarios"]["nominal"]
    return {"section": "2b",
            "claim": f"**Flagship**: the extreme-AO Shack-Hartmann job (`flagship_sh`): the anti-aliasing EOF beats "
                     f"the best classical controller it was given, {NAMES.get(ratios['over'], ratios['over'])}"
                     + (f"; the guard deploys it {guarded}" if guarded else
                        "; the guard keeps the integrator" if guard else ""),
            "number": f"{_x(mine['variance_ratio'])} ({rms(scored[ratios['over']]):.3g} against "
                      f"{rms(scored[best]):.3g} nm over the pupil; {_span(spread)} over {len(spread)} realisations); "
                      f"after the fitting error ({ratios['fitting_nm']:.3g} nm) {_x(mine['after_fitting_variance_ratio'])}"
                      f"; raw contrast at 3 λ/D {_x(contrast['ratio'])} against the "
                      f"{contrast['against'].replace('_', ' ')}, best in contrast there",
            "conditions": "8 m, 40 x 40, r0 15 cm at 500 nm, I = 8, 1 kHz, delay 2, 10 and 20 m/s at 30° and 120°; "
                          f"classical side: {', '.join(NAMES.get(c, c) for c in classical)}, each tuned on a stream "
                          "of its own (PFC left out: its cost at 40 across); the EOFs learn in the very simulation they "
                          "are scored in, on its true phase (simulator knowledge a telescope lacks: its twin is identified from "
                          "telemetry, docs/twin.md); no oracle (no η); "
                          f"{len(spread)} realisations of {scored[best]['n_frames']} frames"}


def study_row() -> dict | None:
    result = load("paper")
    if result is None:
        return None
    nominal, doubled = result["scenarios"]["nominal"], result["scenarios"]["dm_gain_2"]
    cl, integ, pi = nominal["cl_eof"], nominal["integrator"], nominal["pseudo_integrator"]
    ol2, cl2 = doubled["ol_eof"], doubled["cl_eof"]
    ol2_text = f"diverges (frame {ol2['diverged_frame']})" if ol2["diverged"] else f"{rms(ol2):.3g} nm"
    return {"section": "1",
            "claim": "The reference study's baselines reproduce (its EOFs' noise-free floors are the simulator's); "
                     "under a DM that applies 2x the command the closed-loop EOF, retrained, holds and the open-loop "
                     "EOF does not",
            "number": f"{_x((rms(integ) / rms(cl)) ** 2)} (integrator {rms(integ):.3g} nm / closed-loop EOF "
                      f"{rms(cl):.3g} nm); pseudo-integrator {rms(pi):.3g} nm (study 24.3); at 2x: closed-loop EOF "
                      f"{rms(cl2):.3g} nm, open-loop EOF {ol2_text}",
            "conditions": "the study's set-up: 8 m, 40 across, one layer, 1 kHz, delay 2, perfect WFS, HCIPy's layer "
                          "on the actuator grid (its noise-free floor is the simulator's)"}


def zonal_row() -> dict | None:
    result = load("realistic_small")
    if result is None:
        return None
    nominal = result["scenarios"]["nominal"]
    best = _best(nominal, ("ol_eof", "cl_eof"))
    gain = rms(nominal["integrator"]) / rms(nominal[best])
    name = {"ol_eof": "open-loop EOF", "cl_eof": "closed-loop EOF"}[best]
    return {"section": "2b",
            "claim": f"Through an idealised zonal sensor (`realistic_small`, the zonal comparison), the {name} "
                     "beats the best-gain integrator",
            "number": f"{_x(gain ** 2)} ({gain:.2f}x in RMS: {rms(nominal['integrator']):.3g} against "
                      f"{rms(nominal[best]):.3g} nm)",
            "conditions": "8 m, 40 across, two layers, 1 nm WFS noise, 1 kHz, delay 2; the mean phase over each "
                          "subaperture, no slopes, aliasing or photon noise, scored at the actuators; 1 realisation"}


def sh_row() -> dict | None:
    result = load("realistic_sh")
    if result is None:
        return None
    nominal = result["scenarios"]["nominal"]
    best = _best(nominal, ("ol_eof", "cl_eof"))
    integ = nominal["integrator"]
    fitting = (integ.get("error_budget") or {}).get("fitting_nm")
    name = {"ol_eof": "open-loop EOF", "cl_eof": "closed-loop EOF"}[best]
    diverged = [n for n in ("ol_eof", "cl_eof") if nominal[n]["diverged"]]
    return {"section": "2b",
            "claim": f"Through eofnn's Shack-Hartmann at poor seeing (`realistic_sh`) that gain is gone: the "
                     f"{name}, fed the measurements, loses to the best-gain integrator"
                     + ("; the closed-loop EOF's fit is unstable" if "cl_eof" in diverged else ""),
            "number": f"{_x((rms(integ) / rms(nominal[best])) ** 2)} ({rms(nominal[best]):.3g} against "
                      f"{rms(integ):.3g} nm over the pupil"
                      + (f", fitting error {fitting:.0f} nm of it)" if fitting else ")"),
            "conditions": "the zonal comparison's loop through a 39 x 39 Shack-Hartmann, R = 8, r0 = 6 cm at 500 nm "
                          "(fitting error dominates); residual over the pupil; 1 realisation"}


def structure_row() -> dict | None:
    result = load("fair/structure_sh")
    if result is None:
        return None
    found = [r for r in structure_rows(result) if "variance_gain" in r]
    if not found:
        return None
    best = max(found, key=lambda r: r["variance_gain"])
    integ = result["scenarios"]["nominal"]["integrator"]
    label = next(f"{model} {structure} filter, target {target}" for name, structure, target, model in STRUCTURE
                 if name == best["name"])
    plain = (rms(integ) / rms(best["m"])) ** 2
    return {"section": "2b",
            "claim": f"A predictor that sees through the aliasing wins through the same Shack-Hartmann: the {label}",
            "number": f"{_x(plain)} over the best-gain integrator ({rms(best['m']):.3g} against {rms(integ):.3g} nm); "
                      f"after the fitting error {_x(best['variance_gain'])}; contrast at 3 λ/D "
                      f"{_x(best.get('contrast_gain') or math.nan)}",
            "conditions": "trained in simulation on the DM's fit of the true phase (`data.target: dm_fit`); "
                          f"{len(best['realisations']) or 'n/a'} realisations of 2000 frames, paired"}


def map_row() -> dict | None:
    entries = [e for e in where_rows() if not math.isnan(e.get("variance_gain", math.nan))]
    if not entries:
        return None
    plain = [(rms(e["contenders"][e["best_classical"]]) / rms(e["contenders"][e["best_predictor"]])) ** 2
             for e in entries]
    contrast = [e.get("contrast_gain", math.nan) for e in entries]
    wins = sum(p > 1 for p in plain)
    return {"section": "2d",
            "claim": f"Over a wind x magnitude map through eofnn's Shack-Hartmann, the best predictor beats the best "
                     f"classical controller (every one tuned, predictive Fourier control included) at {wins} of "
                     f"{len(entries)} points",
            "number": f"{_span(plain)}; after the fitting error {_span([e['variance_gain'] for e in entries])}; "
                      f"contrast at 3 λ/D {_span(contrast)}",
            "conditions": "the loop at half scale (4 m, 20 across), two layers off the lattice, winds 5-30 m/s, "
                          "R = 8 and 10, r0 = 6 cm at 500 nm; 2 realisations a point"}


def _summed_variance(values: list[float], minus: list[float] | None = None) -> float:
    minus = minus or [0.0] * len(values)
    return sum(v * v - f * f for v, f in zip(values, minus, strict=True))


def oopao_row() -> dict | None:
    from report_oopao import AA_LABELS, ratios, strongest

    # Each magnitude from its longer rerun on the noise-aware reconstructor where it was made (run.sh oopao_long,
    # oopao_long10).
    runs = {mag: load(f"interop/oopao_aa/m{mag}_long", "result") or load(f"interop/oopao_aa/m{mag}", "result")
            for mag in (8, 10)}
    runs = {mag: r for mag, r in runs.items() if r}
    if not runs:
        return None
    plain, after, contrast, eta, bases = [], [], [], [], []
    for mag, r in runs.items():
        g = ratios(r, "eof_measured") or {}
        spread = (g.get("spread") or {}).get("plain") or []
        plain.append(f"{_x(g.get('plain', math.nan))} (I = {mag}"
                     + (f"; {_x(min(spread))}-{_x(max(spread))} over the realisations" if len(spread) > 1 else "")
                     + ")")
        after.append(_x(g.get("after", math.nan)))
        contrast.append(_x(g.get("contrast") or math.nan) + f" (against the {AA_LABELS[g['contrast_against']]})"
                        if g.get("contrast_against") else _x(math.nan))
        if g.get("eta") is not None:
            eta.append(f"{g['eta']:.2f}")
        bases.append(f"{AA_LABELS[strongest(r)[0]]} at I = {mag}")
    statistics = "; ".join(
        f"I = {mag}: {len(r['contenders']['eof_measured']['realisations_median_rms_nm'])} realisations of "
        f"{_scored_frames(r)} scored frames, the {_reconstructor(r)} reconstructor" for mag, r in runs.items())
    oracle = all("oracle" in r["contenders"] for r in runs.values())
    return {"section": "2d",
            "claim": "In OOPAO's loop, a 5 x 5 open-loop EOF fitted on that loop's telemetry alone beats the strongest "
                     "classical controller built from the same telemetry",
            "number": f"{', '.join(plain)}; after the fitting error {', '.join(after)}; contrast at 3 λ/D "
                      f"{', '.join(contrast)}" + (f"; η {', '.join(eta)}" if eta else ""),
            "conditions": f"OOPAO's 8 m, 40 x 40 Shack-Hartmann loop, photon noise, one 20 m/s layer, r0 = 15 cm; "
                          f"integrator, modal integrator, LQG and PFC each tuned in the loop (strongest: "
                          f"{', '.join(bases)})" + ("; η against an oracle trained on OOPAO's truth" if oracle else "")
                          + f"; {statistics}"}


#: The reconstructors of OOPAO's loop (examples/oopao_loop.py --reconstructor), as the findings name them.
RECONSTRUCTORS = {"least_squares": "truncated least-squares", "map": "MAP (the simulator's r0, labelled knowledge)",
                  "map_telemetry": "MAP (turbulence and noise from telemetry)"}


def _reconstructor(result: dict) -> str:
    kind = (result.get("reconstructor") or {}).get("kind", "least_squares")
    return RECONSTRUCTORS.get(kind, kind)


def _scored_frames(result: dict) -> int:
    """Frames scored per realisation of an OOPAO study: ``scored_frames`` where set, else its loop's frames less
    those it settles on."""
    config = result.get("config", {})
    if config.get("scored_frames"):
        return int(config["scored_frames"])
    return int(config.get("loop_frames", 0)) - int(config.get("settle_frames", 0))


def twin_row() -> dict | None:
    from report_oopao import baseline_run, strongest

    plain, after = [], []
    for mag in (8, 10):
        run, pupil = baseline_run(mag), load(f"interop/twin_pupil/m{mag}", "result")
        if not run or not pupil:
            continue
        fit = run["fitting_error_nm"]
        base = run["contenders"][strongest(run)[0]]["realisations_median_rms_nm"]
        p, a = [], []
        for entry in pupil["seeds"].values():
            values = entry["contender"]["realisations_median_rms_nm"]
            if None in values:
                continue
            p.append(_summed_variance(base) / _summed_variance(values))
            a.append(_summed_variance(base, fit) / _summed_variance(values, fit))
        plain.append(f"{_span(p)} (I = {mag}, {len(p)} twin training sets)")
        after.append(_span(a))
    if not plain:
        return None
    row = {"section": "2d",
           "claim": "The same EOF trained in eofnn's own simulation of that system (OOPAO's pupil in the twin, "
                    "nothing of OOPAO's truth) and carried into OOPAO's loop beats its strongest classical controller",
           "number": f"{'; '.join(plain)}; after the fitting error {', '.join(after)}",
           "conditions": "as the row above; the twin at the loop's identified noise, in its reconstructor's modes"}
    identified = twin_identified_row()  # the twin built from the telemetry alone: one more sentence of this row
    if identified:
        row["claim"] += "; trained in a twin identified from OOPAO's telemetry alone, it closes most of the gap to the " \
                        "filter trained on OOPAO's truth"
        row["number"] += f"; identified twin: {identified['number']}"
        row["conditions"] += f"; identified twin: {identified['conditions']}"
    return row


ROWS = (flagship_row, study_row, zonal_row, sh_row, structure_row, map_row, oopao_row, twin_row)


def findings_table(page: str = "") -> str:
    """The findings as a markdown table; ``page`` is prefixed to the links (``experiments/README.md`` from the
    project's README, empty on the page itself)."""
    lines = ["| finding | variance ratio (plain first) | conditions | section |", "|---|---|---|---|"]
    missing = []
    for make in ROWS:
        row = make()
        if row is None:
            missing.append(make.__name__.removesuffix("_row"))
            continue
        title = SECTIONS[row["section"]]
        lines.append(f"| {row['claim']} | {row['number']} | {row['conditions']} | "
                     f"[{row['section']}]({page}#{anchor(title)}) |")
    if missing:
        lines.append(f"| (no summary yet: {', '.join(missing)}) | | | |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(findings_table())
