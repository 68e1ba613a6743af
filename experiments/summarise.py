"""Collect the raw runs under experiments/runs/ into the committed summaries, pages and figures of experiments/.

``experiments/reproduce.sh`` writes every raw output (``eofnn compare``/``sweep`` folders, per-point records,
checkpoints, time series) under the ignored ``experiments/runs/<name>/``. This module keeps, for each experiment,
only what the pages need in the committed ``experiments/<name>/``:

- ``summary.json``: the numbers the pages quote, pruned from the run's ``metrics.json`` (and ``robustness.json``),
  or from a sweep's ``sweep.csv`` and its points' ``metrics.json``;
- the figures (``*.png``) and the run's own pages (``results.md``, ``pareto.md``).

``python experiments/make_report.py --collect`` calls :func:`collect` and then writes experiments/README.md from the
summaries alone; without ``--collect`` it needs no raw run.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
from report_oopao import ANTIALIAS_RUNS, OOPAO_POINTS, TWIN_RUNS
from report_where import plot, rows

HERE = Path(__file__).parent
RUNS = HERE / "runs"

# Every ``eofnn compare`` output the pages read (experiments/<name> <- experiments/runs/<name>).
COMPARES = ("flagship", "paper", "realistic", "fair/alpha_auto", "fair/mlp_budget", "fair/paper_gap/hcipy",
            "fair/paper_gap/exact", "fair/paper_gap/exact_subaperture", "robustness_realistic",
            "robustness_realistic_misregistration", "robustness_study", "vibrations", "adaptive/wind_speed",
            "adaptive/wind_turn", "adaptive/dm_gain_drift", "adaptive/dm_gain_drift_2.0", "elt_small", "elt", "realistic_small",
            "realistic_sh", "fair/moonshot", "fair/moonshot_oracle", "through_loop/noisy", "through_loop/noise_free",
            "fair/structure_sh",
            "where/check_v5", "where/check_v20_m8", "where/check_v20_m10", "where/check_pfc", "where/check_space",
            "where/check_space_10um", "pyramid/contest_m8", "pyramid/contest_m10",
            "pyramid/contest_quick_m8", "pyramid/contest_quick_m10", "pyramid/realistic_pyr_eof",
            "pyramid/realistic_pyr_eof_og")
PROFILED = ("where/check_space", "where/check_space_10um")  # compare runs whose contrast profiles the page integrates
SWEEPS = ("alpha", "history", "frames", "realistic_cl_eof", "realistic_ol_eof")  # experiments/sweeps/<name>
INTEROP = ("hcipy", "oopao", "oopao_aliasing",  # experiments/interop/<name>, written by experiments/interop/run.sh
           *(f"oopao_map/v{wind}_m{mag}" for wind, mag in OOPAO_POINTS))
PAGES = ("results.md", "pareto.md")

# What is kept of each result file: a set keeps those keys whole, a dict descends ("*": every key), True keeps all.
_PER = lambda keep: {"*": {"*": keep}}  # noqa: E731  (scenario -> predictor -> keep)
METRICS = {
    "scenarios": _PER({"median_rms_nm", "diverged", "diverged_frame", "settle_frames", "n_frames", "reconvergence",
                       "fallback_frame", "residual_over", "actuator_median_rms_nm", "error_budget",
                       "spatial_split_nm"}),
    "raw_contrast": {"*": {"*": True}},
    "stability": _PER({"stable", "dm_gain_interval"}),
    "simulated_stability": _PER({"dm_gain_interval", "tolerance"}),
    "integrator_gains": _PER({"gain"}),
    "ridge_alphas": _PER({"alpha": True, "val_loss": True, "unregularised_val_loss": True, "path": {"alpha"}}),
    "searches": _PER({"chosen": {"lr", "best_epoch"}, "budget": {"max_epochs_per_trial"}}),
    "classical_models": _PER({"frames", "modes", "gain_margin"}),
    "fallback": _PER({"per", "integrator_gain", "modes", "n_modes", "predictor_modes", "deployed"}),
    "classical_settings": _PER({"order", "smoothing", "ar_order", "noise_scale", "pfc.alpha", "median_rms_nm"}),
    "verdict": True,
    "realisation_median_rms_nm": True,
    "timings_s": True,
    "peak_memory_bytes": True,
}
ROBUSTNESS = {"keys", "values", "median_rms_nm", "analytic_dm_gain_interval"}
SCORED = ("median_rms_nm", "realisations_median_rms_nm", "mean_of_realisations_nm")  # a contender in the loop
INTEROP_METRICS = {
    "runs": {"*": {"identified": {"dm_gain", "dm_gain_times_optical_gain", "dm_gain_true"},
                   "simulator": {"n_subapertures", "diameter_m", "rcond", "n_seen_modes", "n_actuators"},
                   "eof": {"diverged", "refits", *SCORED},
                   "split": {"integrated_modes", "mix", "gain", "scan", "scan_median_rms_nm", "n_modes", *SCORED},
                   "replay": {"predictor_median_rms_nm", "integrator_median_rms_nm"},
                   "fitting_error": {"median_rms_nm"},
                   "integrator": {"best_gain", "scan", "scan_median_rms_nm", *SCORED}}},
    "budget": {"fitting_error_nm": True, "controllers": {"*": {
        "residual_perfect_sensor_nm", "residual_shack_hartmann_nm", "residual_photon_noise_nm", "temporal_nm",
        "aliasing_nm", "noise_nm"}}},
}
SWEEP_DROPPED = {"status", "mean_rms_nm", "p95_rms_nm", "strehl", "diverged", "diverged_frame", "settle_frames",
                 "n_frames", "error"}  # sweep.csv columns the pages do not quote


def prune(value, keep):
    """``value`` reduced to the keys ``keep`` names (see METRICS), in ``value``'s order."""
    if keep is True or not isinstance(value, dict):
        return value
    if isinstance(keep, set):
        keep = dict.fromkeys(keep, True)
    return {k: prune(v, keep[k] if k in keep else keep["*"]) for k, v in value.items() if k in keep or "*" in keep}


def _contrast_profiles(path: Path, scenario: str) -> dict[str, dict]:
    """Each contender's azimuthally averaged raw contrast against separation (lambda/D, out to the control radius's
    inscribed circle) from a run's ``timeseries.npz``, to 4 significant digits; empty if the run kept none. Plain
    arrays only: ``np.load`` refuses pickled objects."""
    if not path.is_file():
        return {}
    out = {}
    with np.load(path) as data:
        for key in data.files:
            parts = key.split("/")
            if len(parts) == 3 and parts[0] == scenario and parts[2] == "raw_contrast":
                sep = data[f"{scenario}/{parts[1]}/contrast_separation_lod"]
                out[parts[1]] = {"separation_lod": [float(f"{v:.4g}") for v in sep],
                                 "raw_contrast": [float(f"{v:.4g}") for v in data[key]]}
    return out


def _read(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _write(name: str, source: str, parts: dict) -> None:
    target = HERE / name / "summary.json"
    target.parent.mkdir(parents=True, exist_ok=True)
    summary = {"source": f"experiments/runs/{name}/{source}, pruned to the numbers the pages quote", **parts}
    target.write_text(json.dumps(summary, indent=1) + "\n")


def _copy_figures_and_pages(name: str) -> None:
    run, target = RUNS / name, HERE / name
    for file in sorted(run.glob("*.png")) + [run / page for page in PAGES if (run / page).is_file()]:
        shutil.copyfile(file, target / file.name)


def compare_summary(name: str) -> bool:
    metrics = _read(RUNS / name / "metrics.json")
    if metrics is None:
        return False
    parts = {"metrics": prune(metrics, METRICS)}
    if name in PROFILED:
        parts["contrast_profiles"] = {scenario: _contrast_profiles(RUNS / name / "timeseries.npz", scenario)
                                      for scenario in metrics["scenarios"]}
    robustness = _read(RUNS / name / "robustness.json")
    if robustness is not None:
        parts["robustness"] = prune(robustness, ROBUSTNESS)
    _write(name, "metrics.json" + (" and robustness.json" if robustness is not None else ""), parts)
    _copy_figures_and_pages(name)
    return True


def sweep_summary(sweep: str) -> bool:
    name = f"sweeps/{sweep}"
    table = RUNS / name / "sweep.csv"
    if not table.is_file():
        return False
    with table.open() as f:
        rows = [{k: v for k, v in row.items() if k not in SWEEP_DROPPED}
                for row in csv.DictReader(f) if row["status"] == "done"]
    stability: dict[str, dict] = {}
    for row in rows:
        point = _read(RUNS / name / "points" / row["point"] / "run" / "metrics.json") or {}
        stability[row["point"]] = prune(point.get("stability", {}), METRICS["stability"])
    _write(name, "sweep.csv (done points) and points/*/run/metrics.json", {"rows": rows, "stability": stability})
    _copy_figures_and_pages(name)
    return True


def interop_summary(run: str) -> bool:
    name = f"interop/{run}"
    metrics = _read(RUNS / name / "metrics.json")
    if metrics is None:
        return False
    _write(name, "metrics.json", {"metrics": prune(metrics, INTEROP_METRICS)})
    _copy_figures_and_pages(name)
    return True


def json_summary(name: str, file: str) -> bool:
    """A script's own JSON result (experiments/runs/<name>/<file>) kept whole."""
    result = _read(RUNS / name / file)
    if result is None:
        return False
    _write(name, file, {"result": result})
    return True


def _sweep_points(name: str) -> list[tuple[str, dict, dict]] | None:
    """``[(point, swept values, metrics, its scenario)]`` of the points of the sweep experiments/runs/<name>/ that finished, in
    order of their names; None where it has no sweep.csv."""
    table = RUNS / name / "sweep.csv"
    if not table.is_file():
        return None
    with table.open() as f:
        reader = csv.DictReader(f)
        keys = reader.fieldnames[1:reader.fieldnames.index("status")]  # the swept keys (short names)
        done = {row["point"]: {k: json.loads(row[k]) for k in keys} for row in reader if row["status"] == "done"}
    runs = [(point, values, _read(RUNS / name / "points" / point / "run" / "metrics.json"))
            for point, values in sorted(done.items())]
    return [(point, values, metrics, next(iter(metrics["scenarios"]))) for point, values, metrics in runs if metrics]


def map_summary(name: str) -> bool:
    """A sweep drawn as a map (experiments/runs/<name>/): per point its swept values and, per contender, the median
    RMS, its realisations, the error budget and the raw contrast (at 3 lambda/D, at every separation reported, and
    its radial profile); the fallbacks' decisions."""
    if (done := _sweep_points(name)) is None:
        return False
    points = []
    for point, values, metrics, scenario in done:
        profiles = _contrast_profiles(RUNS / name / "points" / point / "run" / "timeseries.npz", scenario)
        contenders = {}
        for contender, m in metrics["scenarios"][scenario].items():
            contenders[contender] = {
                "median_rms_nm": m["median_rms_nm"], "diverged": m["diverged"],
                "realisations_nm": metrics.get("realisation_median_rms_nm", {}).get(scenario, {}).get(contender),
                "error_budget": m.get("error_budget"),
                "raw_contrast_3": (metrics.get("raw_contrast", {}).get(scenario, {}).get(contender) or {}).get("3"),
                "raw_contrast": metrics.get("raw_contrast", {}).get(scenario, {}).get(contender),
                "contrast_profile": profiles.get(contender),
                "spatial_split_nm": m.get("spatial_split_nm")}
        fallback = {c: {"deployed": f.get("deployed"), "why": f.get("why")}
                    for c, f in metrics.get("fallback", {}).get(scenario, {}).items()}
        settings = {c: {k: v for k, v in chosen.items() if k != "scanned"}  # the classical settings scanned and chosen
                    for c, chosen in metrics.get("classical_settings", {}).get(scenario, {}).items()}
        points.append({"point": point, "values": values, "contenders": contenders, "fallback": fallback,
                       "settings": settings})
    _write(name, "points/*/run/metrics.json", {"points": points})
    _copy_figures_and_pages(name)
    if name == "where/sh":
        plot(rows(), HERE / name / "gain_map.png")  # the map's figure, drawn from the summary just written
    return True


def antialias_summary(name: str) -> bool:
    """The anti-aliasing study in another simulator's loop (experiments/runs/<name>/metrics.json of
    ``examples/oopao_loop.py --anti-aliasing``): kept whole, with its results.md."""
    metrics = _read(RUNS / name / "metrics.json")
    if metrics is None:
        return False
    _write(name, "metrics.json", {"result": metrics})
    _copy_figures_and_pages(name)
    return True


#: The contest through OOPAO's pyramid (experiments/interop/run.sh pyramid_contest; experiments/pyramid/README.md).
PYRAMID_CONTEST = ("interop/pyramid_contest/m8", "interop/pyramid_contest/m10")
#: The noise-aware reconstructor in OOPAO's loop (experiments/interop/run.sh map_small).
MAP_SMALL = (*(f"interop/map_small/{rec}{sfx}" for sfx in ("", "_rcond0.02") for rec in ("least_squares", "map")),
             "interop/map_small/map_telemetry")
#: The anti-aliasing EOF in OOPAO's loop (experiments/interop/run.sh oopao_aa), the pyramid's contest and map_small.
ANTIALIAS = (*ANTIALIAS_RUNS, *TWIN_RUNS, *PYRAMID_CONTEST, *MAP_SMALL)

#: Sweeps drawn as maps (experiments/<name> <- experiments/runs/<name>/).
MAPS = ("where/sh", "where/space")  # where/space: check_space.yaml over the map's grid (the spatial split)


#: Sweeps whose points' verdicts carry the oracle: each point's ratios and eta kept (experiments/where/eta_sh.yaml).
ETA_MAPS = ("where/eta",)
#: What is kept of a predictor's (or the oracle's) verdict ratios on an eta map.
ETA_KEPT = ("median_rms_nm", "variance_ratio", "variance_ratio_spread", "rms_ratio", "after_fitting_variance_ratio",
            "after_fitting_variance_ratio_spread", "raw_contrast", "eta", "eta_spread")


def eta_map_summary(name: str) -> bool:
    """A sweep with the oracle in its contest (experiments/runs/<name>/): per point its swept values, each
    contender's median RMS and realisations, and the verdict's ratios over the best classical controller (plain
    variance, RMS, after fitting, raw contrast against the best in contrast, eta; each with its spread)."""
    if (done := _sweep_points(name)) is None:
        return False
    rows = []
    for point, values, metrics, scenario in done:
        ratios = (verdict := metrics["verdict"]["scenarios"][scenario])["ratios"]
        kept = {who: {k: r.get(k) for k in ETA_KEPT} for who, r in ratios["predictors"].items()}
        if ratios.get("oracle"):
            kept["oracle"] = {k: ratios["oracle"].get(k) for k in ETA_KEPT}
        rows.append({"point": point, "values": values, "best_classical": verdict["best_classical"]["name"],
                     "fitting_nm": ratios.get("fitting_nm"), "after_fitting_how": ratios.get("after_fitting_how"),
                     "median_rms_nm": {c: m["median_rms_nm"] for c, m in metrics["scenarios"][scenario].items()},
                     "realisations_nm": metrics.get("realisation_median_rms_nm", {}).get(scenario),
                     "ratios": kept})
    # Points run in parts (experiments/where/eta_grid_10.yaml after the rest): those of the committed summary that
    # this run has not are kept; a point run again replaces its row.
    found = {row["point"] for row in rows}
    earlier = _read(HERE / name / "summary.json") or {}
    rows += [row for row in earlier.get("points", []) if row["point"] not in found]
    _write(name, "points/*/run/metrics.json", {"points": sorted(rows, key=lambda row: row["point"])})
    return True


#: Scripts' JSON results the pages read whole (experiments/<name> <- experiments/runs/<name>/<file>).
JSONS = {"coupled_margins": "realistic_10.json", "interop/twin_seeds": "twin_seeds.json", "interop/rim": "rim.json",
         "interop/twin_pupil/m8": "twin_pupil.json", "interop/twin_pupil/m10": "twin_pupil.json"}


def collect() -> list[str]:
    """Write the summaries, figures and pages of every experiment found under experiments/runs/; return the missing."""
    missing = [n for n in COMPARES if not compare_summary(n)]
    missing += [f"sweeps/{s}" for s in SWEEPS if not sweep_summary(s)]
    missing += [f"interop/{r}" for r in INTEROP if not interop_summary(r)]
    missing += [name for name, file in JSONS.items() if not json_summary(name, file)]
    missing += [name for name in MAPS if not map_summary(name)]
    missing += [name for name in ETA_MAPS if not eta_map_summary(name)]
    missing += [name for name in ANTIALIAS if not antialias_summary(name)]
    return missing
