"""Section 2b of experiments/README.md: the main job through a Shack-Hartmann (experiments/realistic_sh) beside the
same job through the zonal sensor (experiments/realistic_small)."""

from __future__ import annotations

import math

from report_common import NAMES, cell, load, margin, rms, variance_less_fitting

CONTENDERS = ("uncorrected", "integrator", "ol_eof", "cl_eof")
HEADER = ("| scenario | contender | zonal (nm, actuators) | Shack-Hartmann (nm, pupil) | SH, actuators (nm) "
          "| SH budget: fit / alias / noise / temporal (nm) | SH contrast at 3 λ/D | SH stable DM gains |\n"
          "|---|---|---|---|---|---|---|---|\n")


def _budget_cell(m: dict | None) -> str:
    budget = None if m is None else m.get("error_budget")
    if not budget:
        return "—"
    return " / ".join("—" if budget[k] is None else f"{budget[k]:.0f}"
                      for k in ("fitting_nm", "aliasing_nm", "noise_nm", "temporal_nm"))


def _contrast(result: dict, scenario: str, name: str, at: str = "3") -> str:
    value = (result.get("raw_contrast", {}).get(scenario, {}).get(name) or {}).get(at)
    return "—" if value is None else f"{value:.2g}"


def _ratio(result: dict, scenario: str) -> tuple[str, float]:
    """The best predictor's gain over the best-gain integrator in ``scenario`` (median RMS, and in variance)."""
    scenarios = result["scenarios"][scenario]
    integrator = rms(scenarios.get("integrator"))
    best = min(("ol_eof", "cl_eof"), key=lambda n: rms(scenarios.get(n)) if rms(scenarios.get(n)) == rms(
        scenarios.get(n)) else float("inf"))
    value = rms(scenarios.get(best))
    return best, integrator / value


def sh_section() -> str:
    sh, zonal = load("realistic_sh"), load("realistic_small")
    if sh is None:
        return "## 2b. Through a real sensor\n\n(no run yet: `experiments/reproduce.sh` section 2b)\n"
    rows = []
    for scenario in sh["scenarios"]:
        for name in CONTENDERS:
            m_sh = sh["scenarios"][scenario].get(name)
            m_z = None if zonal is None else zonal["scenarios"].get(scenario, {}).get(name)
            stab = sh.get("stability", {}).get(scenario, {}).get(name)
            actuators = None if m_sh is None else m_sh.get("actuator_median_rms_nm")
            rows.append(f"| {scenario} | {NAMES.get(name, name)} | {cell(m_z)} | {cell(m_sh)} | "
                        f"{'' if actuators is None else format(actuators, '.3g')} | "
                        f"{_budget_cell(m_sh)} | {_contrast(sh, scenario, name)} | {margin(stab)} |")
    best, gain = _ratio(sh, "nominal")
    zonal_text = ""
    if zonal is not None:
        zbest, zgain = _ratio(zonal, "nominal")
        zonal_text = (f" Through the zonal sensor the same job gives the {NAMES[zbest]} {zgain:.2f}x the best-gain "
                      f"integrator, scored at the actuators, where there is no fitting error and no aliasing.")
    nominal = sh["scenarios"]["nominal"]
    b_int = (nominal.get("integrator") or {}).get("error_budget") or {}
    b_best = (nominal.get(best) or {}).get("error_budget") or {}

    def term(budget: dict, key: str) -> str:
        return "—" if budget.get(key) is None else f"{budget[key]:.0f}"

    unstable = [NAMES[n] for n in ("ol_eof", "cl_eof") if (nominal.get(n) or {}).get("diverged")]
    unstable_text = (f" The {' and '.join(unstable)} diverged in the nominal plant: its closed-form fit is unstable "
                     "there, as its analysis says." if unstable else "")
    return f"""## 2b. Through a real sensor: the main job's twin on a Shack-Hartmann

**Verdict.** Through a 39 x 39 Shack-Hartmann with photon noise from an R = 8 guide star, the best predictor
({NAMES[best]}) is {gain:.2f}x the best-gain integrator in median RMS over the pupil in the nominal plant: the main
job's gain does not survive a real sensor.{zonal_text}{unstable_text} Over the pupil the residual is the fitting error
({term(b_int, "fitting_nm")} nm, which no controller touches) and the aliasing ({term(b_int, "aliasing_nm")} nm for
the integrator, {term(b_best, "aliasing_nm")} for the {NAMES[best]}), which a predictor fed with the measurements
passes on like the integrator; the temporal term a predictor exists to remove is {term(b_int, "temporal_nm")} nm for
the integrator and {term(b_best, "temporal_nm")} for the {NAMES[best]}, and its noise term {term(b_int, "noise_nm")}
against {term(b_best, "noise_nm")}. One realisation: differences of a few per cent are within its scatter.

`eofnn compare --config configs/realistic_sh.yaml` (`configs/realistic_small.yaml`'s sky, telescope, contenders and
budgets; the sensor: Fried geometry between the 40 x 40 actuators, 4 x 4 phase samples per subaperture, Gaussian
influence functions of coupling 0.35, the least-squares reconstructor with the default cut, photon noise by Rousset's
formula), beside `eofnn compare --config configs/realistic_small.yaml` (the zonal sensor, 1 nm of WFS noise). Median
RMS (nm): the zonal run scores the actuators, the Shack-Hartmann run the pupil (fitting error included; its
command-space RMS at the actuators beside it). The budget splits the Shack-Hartmann run in quadrature from runs
without noise and with a perfect sensor (fitting / aliasing / noise / temporal, nm). Raw contrast at 3 λ/D behind a
perfect coronagraph at 1.65 µm, from the residual over the pupil. One realisation of 3000 frames (2500 scored): a
statistic of one realisation scatters by 10-20%.

""" + HEADER + "\n".join(rows) + """

Limits: the sensor is geometric (no diffraction, no spot truncation, no optical gain), fully lit subapertures, a
single guide-star magnitude; a predictor's perfect-sensor run meets unaliased measurements it was not trained on, so
its temporal term is an upper bound (the integrator's is not); the predictors of this table learn from the
measurements (`s = R S phi`, aliasing included), so they do not try to see through the aliasing (the anti-aliasing
filters of the table below do); the analytic margins assume the measurement of the DM is the command itself, which holds on the
reconstructor's modes and, by construction of the computer's fill, on the modes it cuts.

""" + flagship_text() + structure_text()


#: The flagship's contenders (configs/flagship_sh.yaml), by their names in its metrics.json.
FLAGSHIP = {"integrator": "best-gain integrator", "modal_integrator": "modal integrator (margin tuned)",
            "lqg": "LQG (model and noise scale tuned)", "ol_eof_aa": "anti-aliasing EOF (5 x 5, DM fit)",
            "ol_eof_aa_guarded": "the same, guarded per KL mode"}


def flagship_text() -> str:
    """The flagship's table (experiments/flagship): every contender's residual over the pupil, its spread over the
    realisations, error budget and raw contrast; '' without its summary."""
    result = load("flagship")
    if result is None:
        return ""
    nominal, per = result["scenarios"]["nominal"], result.get("realisation_median_rms_nm", {}).get("nominal", {})
    rows = []
    for name, label in FLAGSHIP.items():
        m = nominal.get(name)
        if m is None:
            continue
        spread = per.get(name) or []
        span = f"{min(spread):.1f}-{max(spread):.1f}" if spread else "—"
        rows.append(f"| {label} | {cell(m)} | {span} | {_budget_cell(m)} | {_contrast(result, 'nominal', name)} |")
    return """### The flagship: extreme AO through the same kind of sensor

`eofnn compare --config configs/flagship_sh.yaml` (the README's first command): 8 m, 40 x 40 actuators, a 39 x 39
Fried Shack-Hartmann with photon noise from an I = 8 guide star, r0 = 15 cm at 500 nm, L0 = 20 m, two layers off the
actuator lattice (10 m/s at 30°, 20 m/s at 120°), 1 kHz, two frames of delay. Every classical controller is tuned on
a stream of its own; PFC is left out (its cost at 40 across). Median RMS over the pupil (nm), its range over the
realisations, the error budget (fitting / aliasing / noise / temporal, nm) and the raw contrast at 3 λ/D (1.65 µm).
The findings table above gives the ratios.

| contender | median RMS (nm, pupil) | realisations (nm) | budget: fit / alias / noise / temporal (nm) | contrast at 3 λ/D |
|---|---|---|---|---|
""" + "\n".join(rows) + "\n\n"


#: Section 2b's second table (experiments/fair/structure_sh.yaml): (name, structure, target, model).
STRUCTURE = (("ol_eof", "own history", "measured", "linear"), ("ol_eof_nb", "3 x 3", "measured", "linear"),
             ("ol_eof_nb_fit", "3 x 3", "DM fit", "linear"), ("ol_eof_aa", "5 x 5", "DM fit", "linear"),
             ("mlp", "own history", "measured", "MLP"), ("mlp_nb", "3 x 3", "measured", "MLP"),
             ("mlp_nb_fit", "3 x 3", "DM fit", "MLP"))


def _less_fitting_nm(m: dict) -> str:
    """The noise-free Shack-Hartmann run's residual less the fitting error, in quadrature (nm): aliasing + temporal."""
    budget = m.get("error_budget") or {}
    total = (budget.get("runs_nm") or {}).get("noise_free")
    if total is None or budget.get("fitting_nm") is None:
        return "—"
    return f"{math.sqrt(max(total ** 2 - budget['fitting_nm'] ** 2, 0.0)):.0f}"


def structure_rows(result: dict) -> list[dict]:
    """Per predictor of the structure table: its numbers and its gain over the best-gain integrator (variance after
    fitting, per realisation paired, and raw contrast at 3 lambda/D)."""
    nominal = result["scenarios"]["nominal"]
    per = result.get("realisation_median_rms_nm", {}).get("nominal", {})
    integrator = nominal["integrator"]
    c_int = (result.get("raw_contrast", {}).get("nominal", {}).get("integrator") or {}).get("3")
    out = []
    for name, structure, target, model in STRUCTURE:
        m = nominal.get(name)
        if m is None:
            continue
        row = {"name": name, "structure": structure, "target": target, "model": model, "m": m,
               "realisations": per.get(name) or []}
        if not m["diverged"]:
            row["variance_gain"] = variance_less_fitting(integrator) / max(variance_less_fitting(m), 1e-30)
            contrast = (result.get("raw_contrast", {}).get("nominal", {}).get(name) or {}).get("3")
            row["contrast_gain"] = c_int / contrast if c_int and contrast else None
            row["paired_nm"] = [p - i for i, p in zip(per.get("integrator") or [], row["realisations"], strict=False)]
        out.append(row)
    return out


def structure_table(result: dict) -> str:
    nominal = result["scenarios"]["nominal"]
    lines = ["| model | inputs | target | median RMS over the pupil (nm) | minus the integrator, per realisation (nm) | "
             "budget: fit / alias / noise / temporal (nm) | variance gain over the integrator, fitting removed | "
             "contrast at 3 λ/D (gain) |", "|---|---|---|---|---|---|---|---|",
             f"| best-gain integrator | | | {cell(nominal['integrator'])} | | {_budget_cell(nominal['integrator'])} | "
             f"1 | {_contrast(result, 'nominal', 'integrator')} |"]
    for row in structure_rows(result):
        paired = ", ".join(f"{d:+.1f}" for d in row.get("paired_nm", []))
        gain = row.get("contrast_gain")
        lines.append(f"| {row['model']} | {row['structure']} | {row['target']} | {cell(row['m'])} | {paired} | "
                     f"{_budget_cell(row['m'])} | {row.get('variance_gain', float('nan')):.3f} | "
                     f"{_contrast(result, 'nominal', row['name'])}"
                     f"{'' if gain is None else f' ({gain:.2f}x)'} |")
    return "\n".join(lines)


def structure_text() -> str:
    """Section 2b's second part: linear against nonlinear, measured against DM-fit targets, through the sensor."""
    result = load("fair/structure_sh")
    if result is None:
        return "(the structure table through the Shack-Hartmann, `experiments/fair/structure_sh.yaml`, not run)\n"
    rows = {r["name"]: r for r in structure_rows(result)}
    best = max((r for r in rows.values() if "variance_gain" in r), key=lambda r: r["variance_gain"])
    linear = [r for r in rows.values() if r["model"] == "linear" and "variance_gain" in r]
    mlps = [r for r in rows.values() if r["model"] == "MLP" and "variance_gain" in r]
    best_mlp = max(mlps, key=lambda r: r["variance_gain"]) if mlps else None
    searches = result.get("searches", {}).get("nominal", {})
    at_last = sum(1 for s in searches.values() if (s.get("chosen") or {}).get("best_epoch")
                  == (s.get("budget") or {}).get("max_epochs_per_trial"))
    budget = (best["m"].get("error_budget") or {})
    integrator = (result["scenarios"]["nominal"]["integrator"].get("error_budget") or {})
    mlp_text = ""
    if best_mlp is not None:
        twin = next((r for r in linear if (r["structure"], r["target"]) == (best_mlp["structure"], best_mlp["target"])),
                    None)
        fit_mlp_m = rows.get("mlp_nb_fit", best_mlp)["m"]
        mlp_text = (f" The best MLP ({best_mlp['structure']}, {best_mlp['target']} target) reaches "
                    f"{best_mlp['variance_gain']:.2f}x"
                    + ("" if twin is None else f", the linear filter with the same inputs and target "
                                               f"{twin['variance_gain']:.2f}x")
                    + f"; on the DM-fit target the MLP does not learn to see through the aliasing (its noise-free "
                    f"residual less fitting {_less_fitting_nm(fit_mlp_m)} nm). {at_last} of {len(searches)} searches "
                    "chose their last "
                    "allowed epoch: the MLP rows are limited by their budget (3 epochs of 6000 frames), as section "
                    "2's were, so this says that a nonlinear model does not earn its place at this budget, not that "
                    "it cannot.")
    return f"""**Structure before nonlinearity, through the Shack-Hartmann** (`eofnn compare --config
experiments/fair/structure_sh.yaml --out experiments/runs/fair/structure_sh`: the loop above in the nominal plant,
section 2's table redone on it with the anti-aliasing predictors among the rows: the same networks trained in
simulation on the DM's fit of the true phase, `data.target: dm_fit`, instead of the measured POL signal. Same 4
frames of measured history, same 6000 training frames, ridge alpha by `alpha: auto`, the MLPs by section 2's
budgeted search; scored over the pupil on 2 realisations of 2000 frames, 1500 settled; the differences to the
integrator are paired, realisation by realisation):

{structure_table(result)}

The anti-aliasing filters win: the {best['structure']} linear filter trained on the DM fit is
{best['variance_gain']:.2f}x the best-gain integrator in residual variance after the fitting error is removed
({', '.join(f'{d:+.1f}' for d in best.get('paired_nm', []))} nm on the two realisations), with
{len(linear)} linear rows between {min(r['variance_gain'] for r in linear):.2f}x and
{max(r['variance_gain'] for r in linear):.2f}x. Its noise-free residual less the fitting error (aliasing and temporal
together) is {_less_fitting_nm(best['m'])} nm against the integrator's
{_less_fitting_nm(result['scenarios']['nominal']['integrator'])}. The budget's split of that between aliasing and
temporal ({budget.get('aliasing_nm', 0):.0f} / {budget.get('temporal_nm', 0):.0f} nm against
{integrator.get('aliasing_nm', 0):.0f} / {integrator.get('temporal_nm', 0):.0f}) does not attribute it for a filter
trained on the DM fit: the split rests on a run with a perfect sensor, whose unaliased measurements such a filter,
built to undo aliasing, was never meant to read, so its "temporal" term there is inflated and its "aliasing" term
deflated by the same amount. The variance it saves is
not at 2-10 λ/D: its raw contrast is {_contrast(result, 'nominal', best['name'])} at 3 λ/D and
{_contrast(result, 'nominal', best['name'], '10')} at 10 λ/D against the integrator's
{_contrast(result, 'nominal', 'integrator')} and {_contrast(result, 'nominal', 'integrator', '10')} (where in the
correction band, which reaches 20 λ/D here, it is saved, contrast at 2-10 λ/D does not tell); the measured-target
3 x 3 filter, whose temporal term is lowest, gives the best contrast at 2-10 λ/D.{mlp_text}
"""
