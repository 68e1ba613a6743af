"""Section 2d of experiments/README.md: where prediction pays through a real sensor (experiments/where/sh, the map of
experiments/where/base_sh.yaml over experiments/where/grid.yaml), and its figure."""

from __future__ import annotations

import math
from pathlib import Path

from report_common import NAMES, fmt, load, variance_less_fitting
from report_eta import eta_map_text
from report_headline import long_run_text
from report_oopao import antialias_text, oopao_map_text, oopao_reading, transfer_text
from report_twin_identified import twin_identified_text

from eofnn.evaluation.budget import temporal_bound as library_temporal_bound
from eofnn.evaluation.contrast import HALO_FROM_LOD
from eofnn.evaluation.contrast import halo as library_halo

CLASSICAL = ("integrator", "lqg", "pfc")
PREDICTORS = ("ol_eof", "ol_eof_nb", "ol_eof_aa", "ol_eof_aa_guarded")
LABELS = {**NAMES, "ol_eof_aa_guarded": "anti-aliasing EOF, guarded",
          "ol_eof_aa": "anti-aliasing EOF (5 x 5, trained on the DM fit)"}


def _held(c: dict) -> bool:
    return not c["diverged"] and c["median_rms_nm"] is not None


def _best(contenders: dict, names: tuple[str, ...]) -> str | None:
    held = [n for n in names if n in contenders and _held(contenders[n])]
    return min(held, key=lambda n: contenders[n]["median_rms_nm"]) if held else None


def _never_worse(integrator: dict, guarded: dict) -> bool:
    """At or below the integrator within the realisations' scatter: its median is, or it is at or below the
    integrator on at least one realisation (both are scored on the same realisations, so the paired differences
    straddle zero); worse on every realisation is worse."""
    paired = [g - i for i, g in zip(integrator.get("realisations_nm") or [], guarded.get("realisations_nm") or [],
                                    strict=False)]
    return guarded["median_rms_nm"] <= integrator["median_rms_nm"] or min(paired, default=1.0) <= 0.0


def _terms(c: dict) -> str:
    b = c.get("error_budget") or {}
    return " / ".join("—" if b.get(k) is None else f"{b[k]:.0f}" for k in ("aliasing_nm", "noise_nm", "temporal_nm"))


def temporal_bound(c: dict) -> float:
    """The largest variance gain (fitting removed) over the contender ``c`` that removing its temporal term alone
    would give (:func:`eofnn.evaluation.budget.temporal_bound`)."""
    return library_temporal_bound(c["median_rms_nm"], c.get("error_budget"))


HALO_FROM = HALO_FROM_LOD  # lambda/D: the halo is integrated from here, leaving out the PSF's core


def halo(c: dict) -> tuple[float, float] | None:
    """``(halo, reach)`` of the contender's radial contrast profile (:func:`eofnn.evaluation.contrast.halo`, from
    HALO_FROM); None without a profile."""
    profile = c.get("contrast_profile")
    if not profile:
        return None
    return library_halo(profile["separation_lod"], profile["raw_contrast"], HALO_FROM)


def rows() -> list[dict]:
    """One entry per point: wind, magnitude, the best of each kind and the gains of predictor over classical."""
    out = []
    for p in load("where/sh", "points") or []:
        values = {key.rsplit(".", 1)[-1]: value for key, value in p["values"].items()}  # dotted keys, last part
        layers, magnitude = values["layers"], values["magnitude"]
        contenders = p["contenders"]
        best_c, best_p = _best(contenders, CLASSICAL), _best(contenders, PREDICTORS)
        entry = {"wind": layers[0]["wind_speed_mps"], "magnitude": magnitude, "best_classical": best_c,
                 "best_predictor": best_p, "contenders": contenders, "fallback": p.get("fallback", {}),
                 "pfc_alpha": (p.get("settings", {}).get("pfc") or {}).get("pfc.alpha")}
        if best_c and best_p:
            c, q = contenders[best_c], contenders[best_p]
            entry["variance_gain"] = variance_less_fitting(c) / max(variance_less_fitting(q), 1e-30)
            cc, qc = c.get("raw_contrast_3"), q.get("raw_contrast_3")
            entry["contrast_gain"] = cc / qc if cc and qc else math.nan
            rc, rq = c.get("raw_contrast") or {}, q.get("raw_contrast") or {}
            entry["contrast_gains"] = {sep: rc[sep] / rq[sep] for sep in rc if rc.get(sep) and rq.get(sep)}
            hc, hq = halo(c), halo(q)
            entry["halo_gain"] = hc[0] / hq[0] if hc and hq else math.nan
            entry["halo_reach"] = hc[1] if hc else math.nan
        out.append(entry)
    return out


def plot(entries: list[dict], path: Path) -> None:
    """Two panels (wind x magnitude): the best predictor's gain over the best classical controller in residual
    variance (fitting error removed) and in raw contrast at 3 lambda/D."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    winds = sorted({e["wind"] for e in entries})
    mags = sorted({e["magnitude"] for e in entries})
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, key, title in zip(axes, ("variance_gain", "contrast_gain"),
                              ("residual variance over the pupil, fitting error removed", "raw contrast at 3 λ/D"),
                              strict=True):
        grid = np.full((len(mags), len(winds)), np.nan)
        for e in entries:
            grid[mags.index(e["magnitude"]), winds.index(e["wind"])] = e.get(key, np.nan)
        image = ax.imshow(np.log2(grid), origin="lower", cmap="RdBu", vmin=-2, vmax=2, aspect="auto")
        for (i, j), value in np.ndenumerate(grid):
            dark = not np.isnan(value) and abs(np.log2(value)) > 1.2  # white on the darkest cells
            ax.text(j, i, "—" if np.isnan(value) else f"{value:.2f}x", ha="center", va="center", fontsize=9,
                    color="white" if dark else "black")
        ax.set_xticks(range(len(winds)), [f"{w:g}" for w in winds])
        ax.set_yticks(range(len(mags)), [f"{m:g}" for m in mags])
        ax.set_xlabel("wind speed of the faster layer (m/s)")
        ax.set_ylabel("guide star R magnitude")
        ax.set_title(f"best predictor / best classical:\n{title}", fontsize=10)
        fig.colorbar(image, ax=ax, label="log2 of the gain (blue: the predictor wins)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def where_section() -> str:
    entries = rows()
    if not entries:
        return "## 2d. Where prediction pays through a real sensor\n\n(experiments/where/sh not run)\n"
    table = ["| wind (m/s) | R mag | best classical (nm) | best predictor (nm) | variance gain, fitting removed | "
             "bound: no temporal term | contrast gain at 3 λ/D | alias / noise / temporal (nm): classical; predictor | "
             "integrator / guarded EOF (nm) | guarded EOF deployed |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    never_worse = []
    for e in sorted(entries, key=lambda e: (e["wind"], e["magnitude"])):
        c = e["contenders"]
        classical = (f"{LABELS.get(e['best_classical'], e['best_classical'])} "
                     f"{fmt(c[e['best_classical']]['median_rms_nm'])}" if e["best_classical"] else "none held")
        predictor = (f"{LABELS.get(e['best_predictor'], e['best_predictor'])} "
                     f"{fmt(c[e['best_predictor']]['median_rms_nm'])}" if e["best_predictor"] else "none held")
        integ, guarded = c.get("integrator"), c.get("ol_eof_aa_guarded")
        pair = ""
        if integ and guarded and _held(integ) and _held(guarded):
            pair = f"{fmt(integ['median_rms_nm'])} / {fmt(guarded['median_rms_nm'])}"
            never_worse.append(_never_worse(integ, guarded))
        deployed = (e["fallback"].get("ol_eof_aa_guarded") or {}).get("deployed") or ""
        bound = temporal_bound(c[e["best_classical"]]) if e["best_classical"] else math.nan
        terms = (f"{_terms(c[e['best_classical']])}; {_terms(c[e['best_predictor']])}"
                 if e["best_classical"] and e["best_predictor"] else "")
        table.append(f"| {e['wind']:g} | {e['magnitude']:g} | {classical} | {predictor} | "
                     f"{e.get('variance_gain', math.nan):.2f}x | {bound:.2f}x | {e.get('contrast_gain', math.nan):.2f}x | "
                     f"{terms} | {pair} | {deployed} |")
    held = sum(never_worse)
    return f"""## 2d. Where prediction pays through a real sensor

{_verdict(entries, held, len(never_worse))}

`eofnn sweep --config experiments/where/base_sh.yaml --grid experiments/where/grid.yaml --out
experiments/runs/where/sh --workers 2`: eofnn's own Shack-Hartmann loop (4 m, 20 x 20 actuators, 19 x 19 Fried
subapertures, photon noise; the pitch and sky of `configs/realistic_sh.yaml` at half its size), two layers of
exact frozen flow at v (30°) and v / 2 (120°), off the actuator lattice, at v = 5, 10, 20 and 30 m/s, and an R = 8
or R = 10 guide star. Every contender is tuned on a stream of its own (the integrator's gain, the LQG's AR order,
the PFC's winds identified from telemetry, ridge alphas on validation frames) and scored over the pupil on 2
realisations of 2000 frames (1700 settled) with its error budget. Contenders: best-gain integrator, LQG (AR per
KL mode) and predictive Fourier control ({_pfc_memory(entries)}), built from dithered-integrator telemetry; the 3 x 3
open-loop EOF on the measured POL signal; the anti-aliasing EOF (5 x 5, trained in simulation on the DM's fit of the
true phase); and that one guarded by the fallback (per KL mode and whole, against the best-gain integrator, on a validation stream
of its own): the one to deploy. Gains are the best classical controller's over the best predictor's (above 1: the
predictor wins) in residual variance after the fitting error is removed, and in raw contrast at 3 λ/D behind a
perfect coronagraph at 1.65 µm. "Bound" is the largest variance gain that removing the best classical
controller's whole temporal term would give with its aliasing and noise left: what a perfect predictor of the
measurement could reach. The 8-point map took 72 min on 2 cores shared with two OOPAO runs (its first run, PFC
untuned: 67 min); R = 6 and R = 12 were cut for time.

![where prediction pays](where/sh/gain_map.png)

{chr(10).join(table)}

{_check_text()}

{_check_v20_text()}

{_check_pfc_text()}

{_check_space_text()}

{eta_map_text()}

**The issue's goal conditions in OOPAO's loop** (`bash experiments/interop/run.sh oopao_aa`, `eofnn/studies/antialias.py`:
OOPAO's 8 m, 40 x 40 Shack-Hartmann with photon noise, one frozen-flow layer at 20 m/s, a DM applying 2x the
command). OOPAO's own loop, closed by a dithered integrator, is recorded on 3 realisations of 2000 frames with
OOPAO's truth beside the telemetry: the DM's fit of the true phase. From those frames come every contender: the
best-gain integrator (gain scanned in OOPAO's loop on a realisation of its own), the modal integrator with optimised
gains (one gain per KL mode, the cap on them chosen on that realisation), the LQG (AR model per KL mode of
the pseudo-open loop, AR order chosen on that realisation), predictive Fourier control (memory scanned past its
grid's edge, alias rings and the reconstructor's coloured noise tried on that realisation), the 5 x 5 open-loop EOF
fitted on the telemetry alone (the measured pseudo-open-loop values, plant identified from the dither), and the
anti-aliasing EOF: the same filter and histories, its targets OOPAO's truth. Beside them, where the table says so,
the oracle: the same open-loop filter trained on OOPAO's truth with 6 taps, a 7 x 7 neighbourhood and 12
recordings (the reach eofnn's own contest gives its oracle): simulator knowledge, a ceiling, never a contender.
The guarded EOF is the anti-aliasing one where it beat the
integrator on the scan realisation, else the integrator. Each is scored on the same 3 further realisations of
1000 frames (900 settled): the mean of their median residual OPD over OOPAO's pupil, the fitting error, and the
raw contrast behind a perfect coronagraph at 1.65 µm from OOPAO's residual OPD every 10th frame.

{antialias_text()}

{long_run_text()}

{oopao_reading()}

{transfer_text()}

{twin_identified_text()}

**The smaller map in OOPAO's loop** (`bash experiments/interop/run.sh oopao_map`: section 6's chain at 20 x 20 on
4 m, one layer at 10 or 20 m/s, photon noise from an I = 8 or 10 guide star, a DM applying 2x the command; the
closed-loop EOF (per actuator) fitted from that loop's own telemetry alone, the split controller, and OOPAO's
best-gain integrator, each scored on 3 realisations: the mean of their median RMS, and their range):

{oopao_map_text()}
"""


def _check_text() -> str:
    """How far two realisations carry: the 5 m/s, R = 8 point again on four other realisations."""
    check = load("where/check_v5")
    if check is None:
        return "(the realisation check, `experiments/where/check_v5.yaml`, not run)"
    per = check.get("realisation_median_rms_nm", {}).get("nominal", {})
    paired = [i - a for i, a in zip(per.get("integrator") or [], per.get("ol_eof_aa") or [], strict=False)]
    nominal = check["scenarios"]["nominal"]
    cell = next((e["contenders"] for e in rows() if (e["wind"], e["magnitude"]) == (5.0, 8.0)), {})
    on_map = [i - a for i, a in zip((cell.get("integrator") or {}).get("realisations_nm") or [],
                                    (cell.get("ol_eof_aa") or {}).get("realisations_nm") or [], strict=False)]
    map_text = ", ".join(f"{d:.1f}" for d in on_map)
    return f"""**How far two realisations carry** (`eofnn compare --config experiments/where/check_v5.yaml --out
experiments/runs/where/check_v5`: the 5 m/s, R = 8 point, the integrator and the anti-aliasing EOF only, on 4
other realisations). The EOF is {fmt(nominal['ol_eof_aa']['median_rms_nm'])} nm against the integrator's
{fmt(nominal['integrator']['median_rms_nm'])}, better by {', '.join(f'{d:.1f}' for d in paired)} nm realisation by
realisation, where the map's two realisations gave {map_text} nm: the anti-aliasing gain at low wind depends on the
realisation, and the guard's validation stream, which found no significant gain there and kept the integrator, was
the better guide. Each cell of the map is two realisations: read differences of a few nm at 5-10 m/s as that."""


V20_HEADER = ("| R mag | best classical (nm) | anti-aliasing EOF (nm) | best classical minus EOF, per realisation (nm) | "
              "variance gain, fitting removed | contrast gain at 3 λ/D |\n|---|---|---|---|---|---|")


def _v20_gain(check: dict) -> tuple[dict, str, float] | None:
    """A 20 m/s check's contenders that held, its best classical controller (integrator, LQG or PFC) and the
    anti-aliasing EOF's variance gain over it after fitting error; None where either side has none."""
    held = {n: m for n, m in check["scenarios"]["nominal"].items() if _held(m)}
    classical = [n for n in ("integrator", "lqg", "pfc") if n in held]
    if not classical or "ol_eof_aa" not in held:
        return None
    best = min(classical, key=lambda n: held[n]["median_rms_nm"])
    return held, best, variance_less_fitting(held[best]) / max(variance_less_fitting(held["ol_eof_aa"]), 1e-30)


def _check_v20_text() -> str:
    """The issue's goal conditions (20 m/s, R = 8 and 10) on 4 realisations the map did not use."""
    lines = []
    for mag in (8, 10):
        check = load(f"where/check_v20_m{mag}")
        found = None if check is None else _v20_gain(check)
        if found is None:
            continue
        held, best, variance = found
        contrast = check.get("raw_contrast", {}).get("nominal", {})
        c_best, c_aa = (contrast.get(best) or {}).get("3"), (contrast.get("ol_eof_aa") or {}).get("3")
        per = check.get("realisation_median_rms_nm", {}).get("nominal", {})
        paired = ", ".join(f"{b - a:.1f}" for b, a in zip(per.get(best) or [], per.get("ol_eof_aa") or [],
                                                           strict=False))
        lines.append(f"| {mag} | {LABELS.get(best, best)} {fmt(held[best]['median_rms_nm'])} | "
                     f"{fmt(held['ol_eof_aa']['median_rms_nm'])} | {paired} | {variance:.2f}x | "
                     f"{(c_best / c_aa if c_best and c_aa else math.nan):.2f}x |")
    if not lines:
        return "(the 20 m/s check, `experiments/where/check_v20.yaml`, not run)"
    return f"""**The issue's goal conditions on more realisations** (`eofnn compare --config experiments/where/check_v20.yaml
--out experiments/runs/where/check_v20_m8`, and with `--scenario.sensor.detector.magnitude 10`: the 20 m/s points,
the best-gain integrator, the LQG, predictive Fourier control with its memory alpha tuned and the anti-aliasing EOF,
with error budgets, on 4 realisations the map did not use; the goal was
1.5x in variance after fitting error and 2x in raw contrast at 3 λ/D):

{V20_HEADER}
{chr(10).join(lines)}"""


SPACE_LABELS = {"integrator": "best-gain integrator", "pfc": "predictive Fourier control",
                "ol_eof_aa": "anti-aliasing EOF"}


def _check_space_text() -> str:
    """Where in spatial frequency the anti-aliasing EOF's variance gain lies (experiments/where/check_space.yaml: the
    map's 20 m/s, R = 8 point, its residual over the pupil split by Parseval inside the control circle, in the
    control square's corners and beyond it)."""
    check, long = load("where/check_space"), load("where/check_space_10um", "contrast_profiles")
    if check is None:
        return "(the spatial split, `experiments/where/check_space.yaml`, not run)"
    runs = check["scenarios"]["nominal"]
    if not all(runs.get(k, {}).get("spatial_split_nm") for k in SPACE_LABELS):
        return "(the spatial split, `experiments/where/check_space.yaml`: a contender diverged or has no split)"
    regions = ("inside_control_circle", "control_square_corners", "beyond_control")
    rows = [f"| {SPACE_LABELS[k]} | {runs[k]['median_rms_nm']:.1f} | "
            + " | ".join(f"{runs[k]['spatial_split_nm'][r]:.1f}" for r in regions) + " |" for k in SPACE_LABELS]

    def gain(base: str) -> str:
        diff = {r: runs[base]["spatial_split_nm"][r] ** 2 - runs["ol_eof_aa"]["spatial_split_nm"][r] ** 2
                for r in regions}
        total = sum(diff.values())
        return (f"{total:.0f} nm² over the {SPACE_LABELS[base]}: " + ", ".join(
            f"{diff[r]:+.0f} ({diff[r] / total:.0%}) {name}" for r, name in zip(
                regions, ("inside the circle", "in the corners", "beyond the square"), strict=True)))

    return f"""**Where in spatial frequency it gains** (`eofnn compare --config experiments/where/check_space.yaml --out
experiments/runs/where/check_space`: the map's 20 m/s, R = 8 point on the map's own 2 realisations, so its residuals
are the map's; each contender's residual over the pupil on the frames the contrast propagates, split exactly
(Parseval on the pupil-masked residual) between the circle inside the control radius, the corners of the DM's
square control region outside it, and beyond the square: `spatial_split_nm` in metrics.json):

| contender | median RMS over the pupil (nm) | inside the circle (nm) | square's corners (nm) | beyond the square (nm) |
|---|---|---|---|---|
{chr(10).join(rows)}

The anti-aliasing EOF's variance gain, region by region: {gain("pfc")}; {gain("integrator")}. Beyond the square
lies the fitting error, the same for every contender, and what the DM's own surface puts there: a filter trained on
the DM's least-squares fit of the phase commands that fit, which the Shack-Hartmann's reconstructor, behind the
classical controllers, does not (our reading). Inside the circle it gains more in variance than its coronagraphic
halo at 1.65 µm shows: {_halo_check(runs, long)}

{_space_map_text()}"""


def _space_map_text() -> str:
    """The spatial split over the whole map (check_space.yaml swept over experiments/where/grid.yaml): per point, the
    share of the anti-aliasing EOF's variance gain over the better of the integrator and PFC that lies inside the
    control circle, in the square's corners and beyond it, and whether the residuals are the map's."""
    points = load("where/space", "points")
    if not points:
        return ("Over the whole map (`eofnn sweep --config experiments/where/check_space.yaml --grid "
                "experiments/where/grid.yaml --out experiments/runs/where/space`): not run.")
    regions = ("inside_control_circle", "control_square_corners", "beyond_control")
    same = {(p["point"], k): c["median_rms_nm"] for p in load("where/sh", "points") or []
            for k, c in p["contenders"].items()}
    cells, worst, inside, beyond, winds = [], 0.0, [], [], []
    for p in sorted(points, key=lambda p: (p["values"]["scenario.atmosphere.layers"][0]["wind_speed_mps"],
                                           p["values"]["scenario.sensor.detector.magnitude"])):
        runs = p["contenders"]
        if not all(runs.get(k, {}).get("spatial_split_nm") for k in SPACE_LABELS):
            continue
        base = min(("integrator", "pfc"), key=lambda k: runs[k]["median_rms_nm"])
        diff = {r: runs[base]["spatial_split_nm"][r] ** 2 - runs["ol_eof_aa"]["spatial_split_nm"][r] ** 2
                for r in regions}
        total = sum(diff.values())
        wind = p["values"]["scenario.atmosphere.layers"][0]["wind_speed_mps"]
        mag = p["values"]["scenario.sensor.detector.magnitude"]
        inside.append(diff["inside_control_circle"] / total)
        beyond.append(diff["beyond_control"] / total)
        winds.append(wind)
        cells.append(f"| {wind:g} | {mag:g} | {SPACE_LABELS[base]} | {total:.0f} | "
                     + " | ".join(f"{diff[r] / total:.0%}" for r in regions) + " |")
        worst = max([worst] + [abs(c["median_rms_nm"] - same[(p["point"], k)]) for k, c in runs.items()
                               if (p["point"], k) in same])
    if not cells:
        return "Over the whole map: no point has all three contenders' splits."

    def wind_of(pick) -> str:  # the wind speed of the point with the smallest or largest share inside the circle
        return f"{winds[inside.index(pick(inside))]:g}"

    return (f"""Over the whole map (`eofnn sweep --config experiments/where/check_space.yaml --grid
experiments/where/grid.yaml --out experiments/runs/where/space`: the same three contenders at every point, on the
map's seed; {"their medians are the map's to the last digit" if worst < 1e-9 else
f"their medians differ from the map's by at most {worst:.2g} nm"}), the anti-aliasing EOF's variance gain over the
better of the integrator and PFC, and its share in each region (inside the circle: {min(inside):.0%} to
{max(inside):.0%}, at {wind_of(min)} and {wind_of(max)} m/s; beyond the square: {min(beyond):.0%} to
{max(beyond):.0%}):

| wind (m/s) | R mag | better classical | gain (nm²) | inside the circle | square's corners | beyond the square |
|---|---|---|---|---|---|---|
""" + "\n".join(cells))


def _halo_check(runs: dict, long: dict | None) -> str:
    """The halo inside the control circle against the split's variance there, at 1.65 µm and at 10 µm
    (experiments/where/check_space_10um: the same runs with evaluation.strehl_wavelength_m 1e-5)."""
    near = load("where/check_space", "contrast_profiles")
    if not near or not long:
        return "why was not measured (the 10 µm run, `check_space_10um`, not run)."

    def ratio(profiles: dict, base: str) -> float:
        h = {k: halo({"contrast_profile": profiles["nominal"][k]})[0] for k in (base, "ol_eof_aa")}
        return h[base] / h["ol_eof_aa"]

    split = {k: runs[k]["spatial_split_nm"]["inside_control_circle"] ** 2 for k in ("pfc", "integrator", "ol_eof_aa")}
    parts = [f"over the {SPACE_LABELS[b]}, {ratio(near, b):.2f}x at 1.65 µm, {ratio(long, b):.2f}x at 10 µm against "
             f"the split's {split[b] / split['ol_eof_aa']:.2f}x" for b in ("pfc", "integrator")]
    return ("the same runs' halo from 0.5 λ/D to the circle's edge, " + "; ".join(parts) + " (`eofnn compare --config "
            "experiments/where/check_space.yaml --evaluation.strehl_wavelength_m 1.0e-5 --out "
            "experiments/runs/where/check_space_10um`). At 10 µm the residual is 0.09 rad and the halo is linear in "
            "the phase, so it measures the split; at 1.65 µm the residual is 0.57 rad and the halo is no longer linear "
            "in it: its higher orders add light that does not follow the split and shrink the ratio, so a "
            "coronagraph at short wavelength sees less of the predictor's gain than the variance does.")


def _check_pfc_text() -> str:
    """Predictive Fourier control's memory alpha at the map's 20 m/s, R = 8 point: as the map ran it, and tuned."""
    check = load("where/check_pfc")
    if check is None:
        return "(the PFC check, `experiments/where/check_pfc.yaml`, not run)"
    nominal = check["scenarios"]["nominal"]
    tuned = (check.get("classical_settings", {}).get("nominal", {}).get("pfc_tuned") or {}).get("pfc.alpha")
    per = check.get("realisation_median_rms_nm", {}).get("nominal", {})

    def rms(name: str) -> str:
        m = nominal.get(name)
        if m is None or not _held(m):
            return "diverged"
        spread = per.get(name) or []
        return fmt(m["median_rms_nm"]) + (f" ({fmt(min(spread))} to {fmt(max(spread))})" if spread else "")

    held = {n: m for n, m in nominal.items() if _held(m)}
    gain = (variance_less_fitting(held["integrator"]) / max(variance_less_fitting(held["pfc_tuned"]), 1e-30)
            if "integrator" in held and "pfc_tuned" in held else math.nan)
    rerun = _map_pfc_alphas(rows()) is not None
    ran = ("The map first ran PFC with its default memory alpha 0.9999 (it now tunes it)" if rerun else
           "The map ran PFC with its default memory alpha 0.9999")
    return f"""**Predictive Fourier control, tuned** (`eofnn compare --config experiments/where/check_pfc.yaml --out
experiments/runs/where/check_pfc`: the map's 20 m/s, R = 8 point on the 4 realisations of the check above). {ran};
in OOPAO's loop that memory proved far too long (below). Here the
best-gain integrator leaves {rms("integrator")} nm, PFC at 0.9999 {rms("pfc")} nm, and PFC with alpha chosen on a
stream of its own (`pfc_alphas: [0.98, 0.99, 0.995, 0.998]`; chosen: {tuned}) {rms("pfc_tuned")} nm: the integrator's
variance after fitting over the tuned PFC's is {gain:.2f}x. """ + ("Hence the map's rerun with `pfc_alphas`." if rerun else
        "Tuned, PFC beats the best-gain integrator here, so the map's gains over the best classical controller, "
        "which did not tune it, are overstated where PFC would have been the best classical controller; the map was "
        "not rerun." if gain > 1 else
        "Even tuned, PFC does not beat the best-gain integrator here, so the map's best classical controller stands "
        "at this point (the other points were not checked).")


def _map_pfc_alphas(entries: list[dict]) -> list | None:
    """PFC's memory alpha chosen at each point of the map, or None where the map ran it untuned (at any point)."""
    alphas = [e.get("pfc_alpha") for e in entries]
    return alphas if alphas and None not in alphas else None


def _pfc_memory(entries: list[dict]) -> str:
    alphas = _map_pfc_alphas(entries)
    if alphas is None:
        return "its memory alpha at the default 0.9999, not tuned: see the check below the map"
    chosen = sorted((e["wind"], e["magnitude"], e["pfc_alpha"]) for e in entries)
    return ("its frozen-flow memory alpha chosen per point on the same stream from 0.98, 0.99, 0.995 and 0.998: "
            + ", ".join(f"{v:g} m/s R = {m:g}: {a:g}" for v, m, a in chosen))


def _verdict(entries: list[dict], held: int, judged: int) -> str:
    """The section's first lines, computed from the map."""
    gains = [e for e in entries if not math.isnan(e.get("variance_gain", math.nan))]
    if not gains:
        return "**Verdict.** No point has both a classical controller and a predictor that held."
    best = max(gains, key=lambda e: e["variance_gain"])
    worst = min(gains, key=lambda e: e["variance_gain"])
    contrast = [e["contrast_gain"] for e in gains if not math.isnan(e.get("contrast_gain", math.nan))]
    kinds = sorted({LABELS.get(e["best_predictor"], e["best_predictor"]) for e in gains})
    over = sum(e["variance_gain"] >= 1.5 for e in gains)
    bounds = [temporal_bound(e["contenders"][e["best_classical"]]) for e in gains]
    beyond = sum(e["variance_gain"] > b for e, b in zip(gains, bounds, strict=True))
    missed = [e for e in entries if (e["fallback"].get("ol_eof_aa_guarded") or {}).get("deployed") == "integrator"
              and _held(e["contenders"].get("ol_eof_aa", {"diverged": True, "median_rms_nm": None}))
              and e["contenders"]["ol_eof_aa"]["median_rms_nm"] < e["contenders"]["integrator"]["median_rms_nm"]]
    where = ", ".join(f"{e['wind']:g} m/s, R = {e['magnitude']:g}" for e in missed)
    missed_text = ("" if not missed else
                   f" At {len(missed)} point(s) ({where}) "
                   "the guard kept the integrator although the anti-aliasing EOF was better on the test stream: "
                   "on its validation stream the gain did not clear 2 standard errors.")
    return (f"**Verdict.** Through a Shack-Hartmann the best predictor ({', '.join(kinds)}) beats the best classical "
            f"controller at {sum(e['variance_gain'] > 1 for e in gains)} of {len(gains)} points, by "
            f"{worst['variance_gain']:.2f}x ({worst['wind']:g} m/s, R = {worst['magnitude']:g}) to "
            f"{best['variance_gain']:.2f}x ({best['wind']:g} m/s, R = {best['magnitude']:g}) in residual variance "
            f"after the fitting error is removed ({over} point(s) at 1.5x or more), and by "
            f"{min(contrast):.2f}x to {max(contrast):.2f}x in raw contrast at 3 λ/D. At {beyond} of {len(gains)} "
            f"points its gain exceeds what a perfect temporal predictor of the measurement could reach (the bound "
            f"column): it wins by seeing through the aliasing. (The budget's split between aliasing and temporal "
            f"does not attribute a DM-fit filter's residual: it rests on a perfect-sensor run, whose unaliased "
            f"measurements such a filter was not built to read; section 2b.) The deployed, guarded "
            f"predictor is at or below the best-gain integrator at {held} of {judged} points (its median is, or it "
            f"is at or below the integrator on one of the two realisations both are scored on).{missed_text}"
            + _contrast_text(gains) + _pfc_caveat(entries))


def _contrast_text(gains: list[dict]) -> str:
    """Where in the focal plane the best predictor's gain lies: at how many points it beats the best classical
    controller in raw contrast at each separation computed, beside how many in variance; and whether the points where
    it wins at 3 lambda/D are those where its budgeted temporal term is below the classical's (empty if the map's
    summary predates contrast at several separations)."""
    seps = sorted({sep for e in gains for sep in e.get("contrast_gains", {})}, key=float)
    if len(seps) < 2:
        return ""
    won = [sum(e["contrast_gains"].get(sep, 0) > 1 for e in gains) for sep in seps]
    counts = ", ".join(f"at {sep} λ/D at {n}" for sep, n in zip(seps, won, strict=True))
    wins = {i for i, e in enumerate(gains) if e["contrast_gains"].get("3", 0) > 1}
    lower = {i for i, e in enumerate(gains)
             if (e["contenders"][e["best_predictor"]].get("error_budget") or {}).get("temporal_nm", math.inf)
             < (e["contenders"][e["best_classical"]].get("error_budget") or {}).get("temporal_nm", -math.inf)}
    same = ("exactly the points where its budgeted temporal term is below the best classical controller's"
            if wins == lower else
            f"{len(wins & lower)} of them among the {len(lower)} where its budgeted temporal term is below the best "
            "classical controller's")
    halos = [e for e in gains if not math.isnan(e.get("halo_gain", math.nan))]
    where = ""
    if halos:
        low, high = min(e["halo_gain"] for e in halos), max(e["halo_gain"] for e in halos)
        reach = min(e["halo_reach"] for e in halos)
        where = (f" Integrated over the focal plane from {HALO_FROM:g} to {reach:.2g} λ/D (the circle inside the "
                 "control radius that the contrast profile covers, each separation weighted by its ring's area), its "
                 f"coronagraphic halo is {low:.2f}x-{high:.2f}x the best classical controller's: a round dark hole "
                 "gains less than the variance says. Where in spatial frequency the variance gain lies is measured "
                 "below (the check of the residual's spatial split).")
    return (f" In raw contrast it beats the best classical controller {counts} of {len(gains)} points, against "
            f"{sum(e['variance_gain'] > 1 for e in gains)} in variance; at 3 λ/D it wins at {same}." + where)


def _pfc_caveat(entries: list[dict]) -> str:
    """What the map's gains are worth with PFC tuned: the 20 m/s, R = 8 point's gain on the map against the check's
    (experiments/where/check_v20.yaml, PFC's alpha tuned), where that check ran."""
    check = load("where/check_v20_m8")
    cell = next((e for e in entries if (e["wind"], e["magnitude"]) == (20.0, 8.0)), None)
    if check is None or cell is None or "pfc" not in check["scenarios"]["nominal"]:
        return ""
    found = _v20_gain(check)
    if found is None:
        return ""
    _, best, gain = found
    where = ("it is the best classical controller" if best == "pfc" else
             f"the best classical controller is still the {LABELS.get(best, best)}")
    if _map_pfc_alphas(entries) is not None:
        return (f" Every classical controller is tuned on the map, predictive Fourier control's memory included; at "
                f"the 20 m/s, R = 8 point the check on 4 other realisations (below) gives the anti-aliasing EOF "
                f"{gain:.2f}x in variance over the best classical controller ({LABELS.get(best, best)}), against "
                f"{cell['variance_gain']:.2f}x on the map's 2.")
    return (f" **But** the map ran predictive Fourier control at its default memory (alpha 0.9999), untuned. Tuned "
            f"(`pfc_alphas`), {where} at the 20 m/s, R = 8 point on 4 other realisations, and the anti-aliasing "
            f"EOF's gain in variance there is {gain:.2f}x, against {cell['variance_gain']:.2f}x on the map. The map's "
            "gains are over a classical side that was not fully tuned: read them as upper bounds until it is rerun "
            "with `pfc_alphas`.")
