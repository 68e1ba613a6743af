"""Section 2c of experiments/README.md: robust by design (experiments/fair/moonshot, experiments/through_loop and
experiments/coupled_margins)."""

from __future__ import annotations

import json
import math

from report_common import HERE, NAMES, fmt, load, rms
from report_fair import CLASSICAL, tuning_text

REQUIRED = (0.8, 1.25)
LABELS = {**NAMES, "ol_eof_nb_4": "open-loop EOF, 3x3 neighbourhood, 4 taps",
          "ol_eof_nb_10": "open-loop EOF, 3x3 neighbourhood, 10 taps",
          "ol_eof_wide_10": "open-loop EOF, 5x5 neighbourhood (radius 2.5), 10 taps",
          "ol_eof_nb_10_range": "open-loop EOF, 3x3 neighbourhood, 10 taps, trained over DM gain 0.8-1.25",
          "cl_eof_range_loop": "closed-loop EOF trained through the loop over DM gain 0.8-1.25"}


def _spread(m: dict | None, medians: list[float] | None) -> str:
    if not medians or m is None or m["diverged"]:
        return ""
    return f" ({fmt(min(medians))}–{fmt(max(medians))})"


def _interval_text(s: dict) -> str:
    """An analytic stable DM-gain interval (a lower bound a rounding below 0 is 0)."""
    if not s:
        return ""
    interval = s.get("dm_gain_interval") if s.get("stable") else None
    return "unstable" if interval is None else f"{max(interval[0], 0.0) + 0.0:.3g}–{interval[1]:.3g}"


def _meets(interval) -> bool:
    return interval is not None and interval[0] <= REQUIRED[0] and interval[1] >= REQUIRED[1]


def _paired(ra: list[float] | None, rb: list[float] | None) -> str:
    """min–max over realisations of ``ra``'s RMS over ``rb``'s (the same turbulence seed each time)."""
    if not ra or not rb:
        return ""
    ratios = [x / y for x, y in zip(ra, rb, strict=True)]
    return f" (per realisation {min(ratios):.2f}x–{max(ratios):.2f}x)"


def moonshot() -> str:
    result = load("fair/moonshot")
    if result is None:
        return "(experiments/fair/moonshot not run)"
    scenario = next(iter(result["scenarios"]))
    metrics, stability = result["scenarios"][scenario], result.get("stability", {}).get(scenario, {})
    spread = result.get("realisation_median_rms_nm", {}).get(scenario, {})
    lines = ["| controller | median RMS (nm), min–max over 3 realisations | stable DM gain (analytic) | "
             "contains [0.8, 1.25] | setting |", "|---|---|---|---|---|"]
    robust = {}
    for name, m in metrics.items():
        s = stability.get(name) or {}
        interval = s.get("dm_gain_interval") if s.get("stable") else None
        text = _interval_text(s)
        value = "diverged" if m["diverged"] else fmt(m["median_rms_nm"])
        lines.append(f"| {LABELS.get(name, name)} | {value}{_spread(m, spread.get(name))} | {text} | "
                     f"{'yes' if _meets(interval) else 'no'} | {tuning_text(result, scenario, name)} |")
        if name not in CLASSICAL and _meets(interval) and not math.isnan(rms(m)):
            robust[name] = rms(m)
    classical = {n: rms(metrics[n]) for n in CLASSICAL if n in metrics and not math.isnan(rms(metrics[n]))}
    best_c = min(classical, key=classical.get)
    if not robust:
        verdict = "No predictor met the constraint."
    else:
        best_p = min(robust, key=robust.get)
        ratio = classical[best_c] / robust[best_p]
        verdict = (f"Best tuned classical controller: {LABELS.get(best_c, best_c)} ({tuning_text(result, scenario, best_c)}), "
                   f"{fmt(classical[best_c])} nm. Best predictor stable over DM gain [0.8, 1.25]: "
                   f"{LABELS.get(best_p, best_p)}, {fmt(robust[best_p])} nm: **{ratio:.2f}x** in RMS "
                   f"({ratio ** 2:.2f}x in variance){_paired(spread.get(best_c), spread.get(best_p))}; the goal was 2x: "
                   f"{'reached' if ratio >= 2 else 'not reached'}.")
    pareto_md = HERE / "fair" / "moonshot" / "pareto.md"
    pareto = pareto_md.read_text().split("\n", 2)[2] if pareto_md.is_file() else "(no pareto.md)"
    return f"""{verdict}

{chr(10).join(lines)}

![pareto](fair/moonshot/pareto.png)

{pareto}"""


def through_loop() -> str:
    """The plant-range and loop-trained filters of configs/through_loop_small.yaml, over DM gain 0.8 / 1 / 1.25."""
    rows = ["| WFS noise | predictor | DM gain 1 | 0.8 | 1.25 | worst / nominal | stable DM gain (analytic) |",
            "|---|---|---|---|---|---|---|"]
    claims = []
    for run, label in (("noise_free", "0 nm"), ("noisy", "5 nm")):
        result = load(f"through_loop/{run}")
        if result is None:
            rows.append(f"| {label} | (experiments/through_loop/{run} not run) | | | | | |")
            continue
        sc = result["scenarios"]
        for name in sc["nominal"]:
            values = [rms(sc[s][name]) for s in ("nominal", "dm_gain_0.8", "dm_gain_1.25")]
            cells = ["diverged" if math.isnan(v) else fmt(v) for v in values]
            worst = (max(values) / values[0]) if not any(math.isnan(v) for v in values) else math.nan
            text = _interval_text(result.get("stability", {}).get("nominal", {}).get(name) or {})
            rows.append(f"| {label} | {name} | " + " | ".join(cells)
                        + f" | {'—' if math.isnan(worst) else f'{worst:.2f}x'} | {text} |")
        for trained in ("ol_eof", "cl_eof"):
            ranged, nominal = f"{trained}_range", trained
            if ranged in sc["nominal"]:
                vals = [rms(sc[s][ranged]) for s in ("nominal", "dm_gain_0.8", "dm_gain_1.25")]
                at_edge = rms(sc["dm_gain_1.25"][nominal])
                claims.append(f"{label}, {trained}: trained over the range, worst {max(vals) / vals[0]:.2f}x its "
                              f"nominal RMS; trained at the nominal plant, at DM gain 1.25 "
                              f"{'diverged' if math.isnan(at_edge) else fmt(at_edge) + ' nm'}")
    return "\n".join(rows) + "\n\n" + "; ".join(claims) + "."


def coupled() -> str:
    file = HERE / "coupled_margins" / "summary.json"
    if not file.is_file():
        return "(experiments/coupled_margins not run)"
    r = json.loads(file.read_text())["result"]
    a, s = r["analytic"], r["simulated"]
    high = "none found" if s["dm_gain_interval"][1] is None else f"{s['dm_gain_interval'][1]:.3f}"
    diff = max(d for d in r["difference"] if d is not None)
    return (f"Neighbourhood EOF at {r['n_actuators']} actuators and {r['history_length']} taps "
            f"({r['companion_rows']} companion rows): analytic DM-gain interval [{a['dm_gain_interval'][0]:.4f}, "
            f"{a['dm_gain_interval'][1]:.4f}] in {a['cpu_seconds']:g} CPU s; closed-loop bisection "
            f"[{s['dm_gain_interval'][0]:.3f}, {high}] (bounds within {s['tolerance']:g}) in {s['cpu_seconds']:g} "
            f"CPU s; largest difference {diff:.3f}.")


OUT_OF_REACH = ("measured out of reach of the best linear predictor the oracle finds from these inputs in this "
                "sensor and loop")


def ceiling() -> str:
    """The moonshot's ceiling (experiments/fair/moonshot_oracle): the oracle's ratio over the best tuned classical
    controller and the share of its gain (eta) the robust predictors reach, on realisations of their own."""
    result = load("fair/moonshot_oracle")
    if result is None:
        return "(experiments/fair/moonshot_oracle not run)"
    scenario = next(iter(result["scenarios"]))
    verdict = result["verdict"]["scenarios"][scenario]
    best_c, oracle, robust = verdict["best_classical"], verdict["ratios"]["oracle"], verdict["ratios"]["predictors"]
    best = max(robust, key=lambda n: robust[n]["variance_ratio"])
    rms_ratio = oracle["rms_ratio"]
    parts = [f"{LABELS.get(n, n)} {fmt(r['median_rms_nm'])} nm: {r['variance_ratio']:.2f}x in variance, "
             f"{r['rms_ratio']:.2f}x in RMS, eta {r['eta']:.2f} "
             f"({r['eta_spread']['min']:.2f}-{r['eta_spread']['max']:.2f} over the realisations)"
             for n, r in robust.items()]
    return (f"Best tuned classical controller {LABELS.get(best_c['name'], best_c['name'])}, "
            f"{fmt(best_c['median_rms_nm'])} nm. The oracle (simulator knowledge: trained on the true turbulence, "
            f"wider and longer than any contender; a bound, not a contender) leaves {fmt(oracle['median_rms_nm'])} nm: "
            f"**{oracle['variance_ratio']:.2f}x in variance, {rms_ratio:.2f}x in RMS** over the best classical "
            f"controller. The robust predictors, as in the moonshot, learn from the simulator's true turbulence "
            f"(`data.truth`: simulator knowledge a telescope lacks), so the oracle differs from them in reach (taps, "
            f"radius, frames), not in knowledge: {'; '.join(parts)}. The moonshot's goal, 2x in RMS, is "
            f"{'within' if rms_ratio >= 2 else 'beyond'} what the oracle reaches ({rms_ratio:.2f}x): "
            f"{'not shown impossible' if rms_ratio >= 2 else OUT_OF_REACH}; in variance the "
            f"best robust predictor, {LABELS.get(best, best)}, reaches {robust[best]['variance_ratio']:.2f}x.")


def robust_section() -> str:
    return f"""## 2c. Robust by design: a robust predictor against the best tuned classical controller

**The moonshot** (`eofnn compare --config experiments/fair/moonshot.yaml --out experiments/runs/fair/moonshot
--pareto noise_1`): `configs/realistic.yaml` at its own 1 nm of WFS noise, seen through the idealised zonal sensor
(the subaperture average: no aliasing; through a Shack-Hartmann see section 2b). Every classical contender tuned on a
stream of its own, as in section 2 (predictive Fourier control included); every predictor learns from 10000 frames
and takes the least-error ridge alpha whose analytic interval contains DM gain [0.8, 1.25]
(`optimization.select`). Three ways to buy that robustness side by side: more taps, a wider neighbourhood, and a
plant range in training (DM gain drawn per 2000-frame training sequence in [0.8, 1.25]); and the closed-loop EOF
trained through the loop over that range. Scored on three realisations of the test turbulence (3000 frames, 2500
settled, each):

{moonshot()}

**Its ceiling** (`eofnn compare --config experiments/fair/moonshot_oracle.yaml --out
experiments/runs/fair/moonshot_oracle`): the best classical pair and the two best robust families above, tuned as
there, with the contest's oracle; they were picked after looking at the moonshot's scored stream, so they are scored
here on new realisations (evaluation seed 11, stated in the config before the run; 3 realisations of 3000 frames):

{ceiling()}

**Robust by training** (`eofnn compare --config configs/through_loop_small.yaml`, noise-free and at 5 nm: a 2 m
telescope, 10 actuators across, one 10 m/s layer, delay 2; 4-tap EOFs from 3000 frames, trained at the nominal plant
or over DM gains drawn in [0.8, 1.25], in closed form or through the loop; median RMS in nm on one test stream):

{through_loop()}

**Margins that scale** (`.venv/bin/python experiments/coupled_margins.py`): {coupled()}
"""
