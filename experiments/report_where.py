"""Section 2d of experiments/README.md: where prediction pays through a real sensor (experiments/where/sh, the map of
experiments/where/base_sh.yaml over experiments/where/grid.yaml), and its figure."""

from __future__ import annotations

import math
from pathlib import Path

from report_common import NAMES, fmt, load

CLASSICAL = ("integrator", "lqg", "pfc")
PREDICTORS = ("ol_eof", "ol_eof_nb", "ol_eof_aa", "ol_eof_aa_guarded")
LABELS = {**NAMES, "ol_eof_aa_guarded": "anti-aliasing EOF, guarded",
          "ol_eof_aa": "anti-aliasing EOF (5 x 5, trained on the DM fit)"}


def _held(c: dict) -> bool:
    return not c["diverged"] and c["median_rms_nm"] is not None


def _best(contenders: dict, names: tuple[str, ...]) -> str | None:
    held = [n for n in names if n in contenders and _held(contenders[n])]
    return min(held, key=lambda n: contenders[n]["median_rms_nm"]) if held else None


def _corrected_variance(c: dict) -> float:
    """Residual variance over the pupil after the fitting error is removed (nm²)."""
    fitting = (c.get("error_budget") or {}).get("fitting_nm") or 0.0
    return max(c["median_rms_nm"] ** 2 - fitting ** 2, 0.0)


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
    """The largest variance gain (fitting removed) over ``c`` that removing its temporal term alone would give: what
    a perfect predictor fed with ``c``'s aliased, noisy measurements could at best reach."""
    b = c.get("error_budget") or {}
    rest = (b.get("aliasing_nm") or 0.0) ** 2 + (b.get("noise_nm") or 0.0) ** 2
    return _corrected_variance(c) / rest if rest > 0 else math.inf


def rows() -> list[dict]:
    """One entry per point: wind, magnitude, the best of each kind and the gains of predictor over classical."""
    out = []
    for p in load("where/sh", "points") or []:
        values = {key.rsplit(".", 1)[-1]: value for key, value in p["values"].items()}  # dotted keys, last part
        layers, magnitude = values["layers"], values["magnitude"]
        contenders = p["contenders"]
        best_c, best_p = _best(contenders, CLASSICAL), _best(contenders, PREDICTORS)
        entry = {"wind": layers[0]["wind_speed_mps"], "magnitude": magnitude, "best_classical": best_c,
                 "best_predictor": best_p, "contenders": contenders, "fallback": p.get("fallback", {})}
        if best_c and best_p:
            c, q = contenders[best_c], contenders[best_p]
            entry["variance_gain"] = _corrected_variance(c) / max(_corrected_variance(q), 1e-30)
            cc, qc = c.get("raw_contrast_3"), q.get("raw_contrast_3")
            entry["contrast_gain"] = cc / qc if cc and qc else math.nan
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
            ax.text(j, i, "—" if np.isnan(value) else f"{value:.2f}x", ha="center", va="center", fontsize=9)
        ax.set_xticks(range(len(winds)), [f"{w:g}" for w in winds])
        ax.set_yticks(range(len(mags)), [f"{m:g}" for m in mags])
        ax.set_xlabel("wind speed of the faster layer (m/s)")
        ax.set_ylabel("guide star R magnitude")
        ax.set_title(f"best predictor / best classical:\n{title}", fontsize=10)
        fig.colorbar(image, ax=ax, label="log2 of the gain (blue: the predictor wins)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


OOPAO_POINTS = tuple((wind, mag) for wind in (10, 20) for mag in (8, 10))  # experiments/interop/run.sh oopao_map


def _nm(value: float | None) -> str:
    return "—" if value is None else fmt(value)


def _spread(c: dict) -> str:
    values = c.get("realisations_median_rms_nm") or []
    return f" ({min(values):.1f}-{max(values):.1f})" if len(values) > 1 else ""


def oopao_map_text() -> str:
    """The smaller map in OOPAO's loop: per point the best-gain integrator, the closed-loop EOF fitted from that
    loop's telemetry alone and the split controller, with the variance gain after the fitting error is removed."""
    lines = ["| wind (m/s) | I mag | fitting error (nm) | best-gain integrator (nm) | closed-loop EOF (nm) | split (nm) | "
             "best eofnn / integrator, variance less fitting | replay: EOF / integrator (nm) |",
             "|---|---|---|---|---|---|---|---|"]
    for wind, mag in OOPAO_POINTS:
        run = ((load(f"interop/oopao_map/v{wind}_m{mag}") or {}).get("runs") or {}).get("shack_hartmann_photon_noise")
        if not run:
            continue
        fit = (run.get("fitting_error") or {}).get("median_rms_nm") or 0.0
        integ, eof, split = run["integrator"], run["eof"], run.get("split") or {}
        ours = [c["median_rms_nm"] for c in (eof, split) if c.get("median_rms_nm") is not None and not c.get("diverged")]
        gain = ((integ["median_rms_nm"] ** 2 - fit ** 2) / max(min(ours) ** 2 - fit ** 2, 1e-30)) if ours else math.nan
        eof_text = "diverged" if eof.get("diverged") else f"{fmt(eof['median_rms_nm'])}{_spread(eof)}"
        split_text = f"{fmt(split['median_rms_nm'])}{_spread(split)}" if split.get("median_rms_nm") else "—"
        replay = run.get("replay") or {}
        lines.append(f"| {wind} | {mag} | {fit:.1f} | {fmt(integ['median_rms_nm'])}{_spread(integ)} "
                     f"(gain {integ.get('best_gain')}) | {eof_text} | {split_text} | {gain:.2f}x | "
                     f"{_nm(replay.get('predictor_median_rms_nm'))} / {_nm(replay.get('integrator_median_rms_nm'))} |")
    if len(lines) == 2:
        return "(the OOPAO map, `bash experiments/interop/run.sh oopao_map`, not run)"
    return "\n".join(lines)


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

`eofnn sweep --config experiments/where/base_sh.yaml --grid experiments/where/grid.yaml --out
experiments/runs/where/sh --workers 2`: eofnn's own Shack-Hartmann loop (4 m, 20 x 20 actuators, 19 x 19 Fried
subapertures, the pitch and sky of `configs/realistic_sh.yaml`: half its size, so that 16 points fit in an hour on 2
cores), two layers of exact frozen flow at v (30°) and v / 2 (120°), photon noise from an R-band guide star. Every
contender tuned on a stream of its own (the integrator's gain, the LQG's AR order; the PFC's winds identified; ridge
alphas on validation frames); scored over the pupil on 2 realisations of 2000 frames (1700 settled). The gain is the
best classical controller's (best-gain integrator, LQG, PFC) over the best predictor's, in residual variance after
the fitting error is removed (above 1: the predictor wins) and in raw contrast at 3 λ/D:

![where prediction pays](where/sh/gain_map.png)

{chr(10).join(table)}

**Never worse**: the guarded neighbourhood EOF (the fallback per Karhunen-Loeve mode against the best-gain
integrator, decided on a validation stream of its own) is at or below the best-gain integrator at {held} of
{len(never_worse)} points (its median is, or it is at or below the integrator on one of the two realisations both
are scored on; worse on both is worse).
"""
