"""Section 2d's eta map: every predictor's share of the oracle's gain over wind speed and seeing, through eofnn's
Shack-Hartmann (experiments/where/eta_sh.yaml over eta_grid.yaml; summary written by summarise.eta_map_summary)."""

from __future__ import annotations

from report_common import NAMES, load

LABELS = {**NAMES, "ol_eof_aa": "anti-aliasing EOF (5 x 5, DM fit)", "ol_eof_nb": "open-loop EOF (3 x 3, measured)"}
#: The points of experiments/where/eta_grid.yaml (3 winds x 2 seeings).
GRID_POINTS = 6
COMMAND = ("eofnn sweep --config experiments/where/eta_sh.yaml --grid experiments/where/eta_grid.yaml "
           "--out experiments/runs/where/eta --workers 1`; its 10 m/s row was run last, alone: `eofnn sweep --config "
           "experiments/where/eta_sh.yaml --grid experiments/where/eta_grid_10.yaml --out experiments/runs/where/eta "
           "--workers 1")


def _value(values: dict, key: str):
    """A swept value by the end of its key (the sweep's short names)."""
    return next((v for k, v in values.items() if k.endswith(key)), None)


def _span(spread: dict | None) -> str:
    return "" if not spread else f" ({spread['min']:.2f}-{spread['max']:.2f})"


def _contrast(r: dict) -> str:
    c = (r.get("raw_contrast") or {}).get("3")
    if not c or c.get("ratio") is None:
        return "—"
    return f"{c['ratio']:.2f}x{_span(c.get('spread'))} ({LABELS.get(c['against'], c['against'])})"


def eta_rows(summary: dict) -> list[dict]:
    """One entry per point and predictor: wind, r0, the best classical controller, the plain/after-fitting/contrast
    ratios and eta with their spreads; sorted by r0 then wind."""
    out = []
    for p in summary["points"]:
        layers, r0 = _value(p["values"], "layers"), _value(p["values"], "r0_m")
        wind = layers[0]["wind_speed_mps"] if layers else None
        oracle = p["ratios"].get("oracle") or {}
        for name, r in p["ratios"].items():
            if name == "oracle":
                continue
            out.append({"wind": wind, "r0": r0, "name": name, "best_classical": p["best_classical"],
                        "classical_nm": p["median_rms_nm"].get(p["best_classical"]), "predictor_nm": r["median_rms_nm"],
                        "oracle_nm": oracle.get("median_rms_nm"), "oracle_plain": oracle.get("variance_ratio"),
                        "fitting_nm": p.get("fitting_nm"), **r})
    return sorted(out, key=lambda e: (e["r0"], e["wind"], e["name"]))


def eta_map_text() -> str:
    summary = load("where/eta", "points")
    if not summary:
        return f"**The oracle's share over wind and seeing** (`{COMMAND}`): not run."
    rows = eta_rows({"points": summary})
    table = ["| r0 at 500 nm (cm) | wind v (m/s) | best classical (nm) | predictor (nm) | oracle (nm) | plain variance "
             "ratio | RMS ratio | after fitting | raw contrast at 3 λ/D (against the best in contrast) | η | oracle's "
             "plain ratio |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for e in rows:
        after = "—" if e["after_fitting_variance_ratio"] is None else \
            f"{e['after_fitting_variance_ratio']:.2f}x{_span(e['after_fitting_variance_ratio_spread'])}"
        eta = "—" if e["eta"] is None else f"{e['eta']:.2f}{_span(e['eta_spread'])}"
        table.append(f"| {100 * e['r0']:.0f} | {e['wind']:g} | {LABELS.get(e['best_classical'], e['best_classical'])} "
                     f"{e['classical_nm']:.1f} | {LABELS.get(e['name'], e['name'])} {e['predictor_nm']:.1f} | "
                     f"{e['oracle_nm']:.1f} | {e['variance_ratio']:.2f}x{_span(e['variance_ratio_spread'])} | "
                     f"{e['rms_ratio']:.2f}x | {after} | {_contrast(e)} | {eta} | {e['oracle_plain']:.2f}x |")
    etas = {name: [e["eta"] for e in rows if e["name"] == name and e["eta"] is not None]
            for name in dict.fromkeys(e["name"] for e in rows)}
    reach = "; ".join(f"the {LABELS.get(n, n)} {min(v):.2f} to {max(v):.2f}" for n, v in etas.items() if v)
    n_points = len(summary)
    cut = "" if n_points >= GRID_POINTS else (f" Only {n_points} of the grid's {GRID_POINTS} points ran (in the order "
                                              "20, 30, 10 m/s, each at 6 then 15 cm); the sweep was stopped for time.")
    return f"""**The oracle's share over wind and seeing** (`{COMMAND}`; the map's system at R = 8, two layers at v (30°)
and v / 2 (120°), r0 6 cm (the map's seeing) and 15 cm at 500 nm, v = 10, 20, 30 m/s; the integrator, the LQG and
PFC tuned as above; 2 realisations of 2000 frames a point; the oracle: the open-loop filter trained on the
simulator's true future turbulence with more taps, reach and data than any contender, simulator knowledge and a
ceiling, not a contender). Ratios are the best classical controller's over the predictor's (above 1: the predictor
is better), in brackets the least and greatest over the realisations; η = (σ² classical − σ² predictor) /
(σ² classical − σ² oracle) in plain variance. Over the point(s) run, η reaches: {reach}.{cut}

{chr(10).join(table)}"""
