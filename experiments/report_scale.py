"""Sections of experiments/README.md on scale and on other simulators: the ELT-class loop (experiments/elt_small)."""

from __future__ import annotations

import math
import textwrap

from report_common import NAMES, cell, load, margin

from eofnn.training.alpha import NEGLIGIBLE_CHANGE, unregularised_change

NAMES_ELT = {**NAMES, "cl_eof_nb": "closed-loop EOF, neighbourhood"}


def _tuning(result: dict, name: str) -> str:
    gains = result.get("integrator_gains", {}).get("nominal", {}).get(name)
    if gains:
        return f"gain {gains['gain']:.3g}"
    alpha = result.get("ridge_alphas", {}).get("nominal", {}).get(name)
    return f"α {alpha['alpha']:.2g}" if alpha else ""


def elt_section() -> str:
    result = load("elt_small")
    if result is None:
        return "## 5. An ELT-class loop\n\n(experiments/elt_small not run)\n"
    metrics = result["scenarios"]["nominal"]
    peaks = result.get("peak_memory_bytes", {})
    lines = ["| controller | median RMS (nm) | tuned on validation | stable DM gain (analytic) | time (s) | peak memory "
             "after the step (GB) |", "|---|---|---|---|---|---|"]
    for name, m in metrics.items():
        stability = result.get("stability", {}).get("nominal", {}).get(name)
        linear = name not in ("uncorrected",)
        interval = margin(stability) if stability else ("not analysed (coupled, 5024 actuators)" if linear else "")
        peak = peaks.get(f"nominal/{name}")
        lines.append(f"| {NAMES_ELT.get(name, name)} | {cell(m)} | {_tuning(result, name)} | {interval} | "
                     f"{result['timings_s'].get(f'nominal/{name}', float('nan')):.0f} | "
                     f"{'' if peak is None else f'{peak / 1e9:.1f}'} |")
    first = next(iter(metrics.values()))
    return f"""## 5. An ELT-class loop: 5024 actuators on one CPU machine

`eofnn compare --config configs/elt_small.yaml --out experiments/runs/elt_small`: `configs/elt.yaml`'s 39 m
telescope, 80 actuators across (5024 active, pitch 0.49 m), three layers of exact frozen flow blowing at 30, 150 and 260
degrees (8, 12 and 20 m/s), seen through each subaperture, 1 nm of WFS noise, 1 kHz, two-frame delay. Every
predictor learns as an observatory would, from telemetry alone (2000 frames of dithered-integrator telemetry, the
plant identified from the dither, 500 validation frames for `alpha: auto`); the integrator's gain is a refined scan
on a stream of its own. Median RMS over {first['n_frames'] - first['settle_frames']} settled frames of one test stream;
time and peak resident memory of the process after each step (each step builds its own streams; the turbulence
screens are shared between steps):

{chr(10).join(lines)}

- The neighbourhood filters' coupled stability analysis is refused at this size (its companion matrix exceeds
  20000 rows; `eofnn.analysis.block`); their DM-gain interval can be measured by simulation
  (`--simulated_margins`), which this short run does not do.
- *Limits*: short telemetry (2000 frames) and test stream; one realisation.

{elt_full_section()}"""


def _interval(result: dict, scenario: str, name: str) -> str:
    """The stable DM-gain interval of a controller: analytic where the linear analysis ran, else simulated."""
    analytic = result.get("stability", {}).get(scenario, {}).get(name)
    if analytic:
        return margin(analytic) + " (analytic)"
    simulated = result.get("simulated_stability", {}).get(scenario, {}).get(name)
    if simulated:
        low, high = simulated["dm_gain_interval"]
        return f"{low:.3g}–{high:.3g} (simulated, bounds within {simulated['tolerance']:g})"
    return ""


def elt_full_section() -> str:
    result = load("elt")
    if result is None:
        return "**The full comparison** (`configs/elt_scao.yaml`): not run.\n"
    scenarios = result["scenarios"]
    peaks = result.get("peak_memory_bytes", {})
    lines = ["| controller | nominal median RMS (nm) | DM applying 2x: median RMS (nm) | tuned on validation (nominal) "
             "| stable DM gain (nominal) | time, nominal (s) | peak memory after the nominal step (GB) |",
             "|---|---|---|---|---|---|---|"]
    for name, m in scenarios["nominal"].items():
        other = scenarios.get("dm_gain_2", {}).get(name)
        peak = peaks.get(f"nominal/{name}")
        lines.append(f"| {NAMES_ELT.get(name, name)} | {cell(m)} | {cell(other)} | {_tuning(result, name)} | "
                     f"{_interval(result, 'nominal', name)} | "
                     f"{result['timings_s'].get(f'nominal/{name}', float('nan')):.0f} | "
                     f"{'' if peak is None else f'{peak / 1e9:.1f}'} |")
    first = next(iter(scenarios["nominal"].values()))
    total = sum(result["timings_s"].values())
    return f"""**The full comparison** (`eofnn compare --config configs/elt_scao.yaml --out experiments/runs/elt
--simulated_margins '[nominal]'`): the same loop, 8000 frames of telemetry per predictor (2000 more for
validation), the neighbourhood filters too, a scenario whose DM applies 2x the command (the open-loop filters are
trained in the nominal plant, the closed-loop ones in each), and the neighbourhood filters' DM-gain interval measured
by closed-loop simulation. Median RMS over {first['n_frames'] - first['settle_frames']} settled frames of one test
stream; the steps of both scenarios took {total:.0f} s on 2 cores, the process's peak resident memory
{max(peaks.values(), default=0) / 1e9:.1f} GB:

{chr(10).join(lines)}

- Per-actuator and neighbourhood EOF learnt from telemetry alone take the integrator's 11 nm to about 3 nm; the
  open-loop filters, whose pseudo-open-loop values assume the nominal DM, diverge when the DM applies 2x, the
  closed-loop ones learn that plant (the study's result, at 5024 actuators).
{_lower_end(result)}- *Limits*: one realisation; the best-gain integrator sits at 94% of its critical gain in the nominal plant.
"""


def _lower_end(result: dict) -> str:
    """A bullet on the ridge alphas chosen at the lower end of their path: how far the unregularised fit's validation
    error is from theirs (the measure of whether a smaller alpha could matter)."""
    ends = [c for choices in result.get("ridge_alphas", {}).values() for c in choices.values()
            if c["alpha"] == c["path"]["alpha"][0]]
    if not ends:
        return ""
    changes = [unregularised_change(c) for c in ends]
    total = sum(len(choices) for choices in result["ridge_alphas"].values())
    text = f"- {len(ends)} of the {total} ridge alphas sit at the lower end of the path ({ends[0]['alpha']:g})"
    if None in changes:
        return text + "; the path could be extended below.\n"
    worst = max(changes, key=abs)
    verdict = ("the telemetry is long enough that these fits need no ridge, and a smaller alpha would not change them "
               "measurably" if abs(worst) < NEGLIGIBLE_CHANGE else "the path should be extended below")
    return textwrap.fill(text + f"; the unregularised fit's validation error differs from theirs by at most "
                         f"{abs(worst):.1e} (relative): {verdict}.", 117, subsequent_indent="  ") + "\n"


def _in_loop(contender: dict | None) -> str:
    """A contender's residual in the loop: the mean of its medians over the scored realisations (nm), each in
    brackets when there are several; ``diverged`` where one did not hold."""
    if not contender:
        return "(not run)"
    medians = contender.get("realisations_median_rms_nm", [contender["median_rms_nm"]])
    if None in medians and len(medians) > 1:
        each = ", ".join("diverged" if m is None else f"{m:.1f}" for m in medians)
        return f"diverged on {medians.count(None)} of {len(medians)} ({each})"
    if None in medians or contender.get("diverged"):
        return "diverged"
    each = f" ({', '.join(f'{m:.1f}' for m in medians)})" if len(medians) > 1 else ""
    return f"{sum(medians) / len(medians):.1f}{each}"


def _interop_rows(path: str, title: str) -> list[str]:
    result = load(path)
    if result is None:
        return [f"| {title} | (not run) | | | | | |"]
    rows = []
    for run, r in result["runs"].items():
        ident, sim, split = r["identified"], r["simulator"], r.get("split")
        target = ident.get("dm_gain_times_optical_gain", ident.get("dm_gain_true"))
        chosen = ("" if not split or split["integrated_modes"] is None
                  else f"; split: {split['integrated_modes']} of {split['n_modes']} integrated, mix {split['mix']:g}")
        rows.append(f"| {title}, {sim['n_subapertures']} x {sim['n_subapertures']}, {sim['diameter_m']:g} m, "
                    f"{run.replace('_', ' ')} | {ident['dm_gain']:.4f} ({target:.4f}) | "
                    f"{r['replay']['predictor_median_rms_nm']:.1f} / {r['replay']['integrator_median_rms_nm']:.1f} | "
                    f"{_in_loop(r['integrator'])} | {_in_loop(r['eof'])} | {_in_loop(split)} | "
                    f"gain {r['integrator']['best_gain']:g}{chosen} |")
    return rows


def _pairs(run: dict, contender: str) -> list[tuple[float | None, float]]:
    """``contender``'s median on each scored realisation beside the integrator's (None where it diverged)."""
    return list(zip(run[contender]["realisations_median_rms_nm"], run["integrator"]["realisations_median_rms_nm"],
                    strict=True))


def _wins(pairs: list[tuple[float | None, float]]) -> int:
    """On how many realisations the contender left less than the integrator (a divergence loses)."""
    return sum(a is not None and a < b for a, b in pairs)


def _small_split_text(small_runs: dict) -> str:
    """The 20 x 20 Shack-Hartmann runs (without and with photon noise): split against integrator, in words."""
    parts = []
    for name, label in (("shack_hartmann", "without noise"), ("shack_hartmann_photon_noise", "with photon noise")):
        run = small_runs.get(name)
        if not run or not (run.get("split") or {}).get("mean_of_realisations_nm"):
            continue
        pairs = _pairs(run, "split")
        parts.append(f"{label} {run['split']['mean_of_realisations_nm']:.1f} against "
                     f"{run['integrator']['mean_of_realisations_nm']:.1f} nm (lower on {_wins(pairs)} of {len(pairs)})")
    return f"At 20 x 20 the split leaves {'; '.join(parts)}. " if parts else ""


def _eof_diverged(runs: list[tuple[str, dict]]) -> str:
    """How often the EOF alone diverged on the scored realisations of the runs ``(label, run)``."""
    said = []
    for label, run in runs:
        medians = run["eof"].get("realisations_median_rms_nm", [])
        if None in medians:
            said.append(f"{medians.count(None)} of {len(medians)} realisations {label}")
    return f" (it diverged on {', '.join(said)}: a filter fitted at the edge of stability)" if said else ""


def _split_finding(big_runs: dict, small_runs: dict) -> str:
    """The 40 x 40 Shack-Hartmann result in words, from its numbers (and the 20 x 20 perfect sensor's choice)."""
    run = next(iter(big_runs.values()), None)
    perfect = (small_runs.get("perfect") or {}).get("split") or {}
    perfect_text = ("" if perfect.get("integrated_modes") is None else
                    f"With the perfect sensor (20 x 20) the same scan chose L = {perfect['integrated_modes']} and mix "
                    f"{perfect['mix']:g}: without aliasing there was nothing to hold back. ")
    if not run or not run.get("split") or run["split"]["integrated_modes"] is None:
        return "- (the 40 x 40 split was not run)"
    split, integ, eof = run["split"], run["integrator"], run["eof"]
    scan, small_text = split["scan"], _small_split_text(small_runs)
    pairs = _pairs(run, "split")
    wins = _wins(pairs)
    removed = math.sqrt(max(integ["mean_of_realisations_nm"] ** 2 - split["mean_of_realisations_nm"] ** 2, 0))
    verdict = ("beats the best-gain integrator" if wins == len(pairs) else
               f"does not beat the best-gain integrator on every realisation ({wins} of {len(pairs)})")
    differences = [b - a for a, b in pairs if a is not None]
    low, high = min(differences), max(differences)
    mean_split, mean_integ = split["mean_of_realisations_nm"], integ["mean_of_realisations_nm"]
    return f"""- **The split {verdict} in OOPAO's 40 x 40 Shack-Hartmann loop**: {mean_split:.1f} against
  {mean_integ:.1f} nm, lower on {wins} of {len(pairs)} realisations (differences {low:.1f} to {high:.1f} nm;
  {removed:.0f} nm removed in quadrature), where the EOF alone leaves {eof['mean_of_realisations_nm']:.1f} nm. Its
  scan chose to keep {split['integrated_modes']} of {split['n_modes']} modes on the integrator and a share
  {split['mix']:g} of the EOF's command on the rest. On that scan realisation the EOF alone left {
      scan['0, 1']:.1f} nm, the integrator {integ['scan_median_rms_nm']:.1f}; keeping the {split['integrated_modes']}
  lowest-order modes on the integrator took the unmixed EOF to {scan[f"{split['integrated_modes']}, 1"]:.1f} nm and
  the mix to {split['scan_median_rms_nm']:.1f}. {small_text}{perfect_text}Our reading: the mix lowers the
  bandwidth at which the EOF passes what it predicts of the aliasing (frozen flow too, so predictable); the gain is
  a few percent, not the temporal error's halving that the perfect sensor shows."""


def interop_section() -> str:
    rows = (_interop_rows("interop/hcipy", "HCIPy")
            + _interop_rows("interop/oopao_aliasing", "OOPAO")
            + _interop_rows("interop/oopao", "OOPAO"))
    small = load("interop/oopao_aliasing") or {"runs": {}}
    budget, small_runs = small.get("budget"), small["runs"]
    big_runs = (load("interop/oopao") or {"runs": {}})["runs"]
    big = next(iter(big_runs.values()))["simulator"] if big_runs else {"rcond": 0, "n_seen_modes": 0, "n_actuators": 0}
    sh_runs = [(f"at 20 x 20 {k.replace('_', ' ')}", r) for k, r in small_runs.items() if k.startswith("shack")]
    sh_runs += [(f"at 40 x 40 {k.replace('_', ' ')}", r) for k, r in big_runs.items()]
    n_scored = len(next(iter(big_runs.values()), {}).get("integrator", {}).get("realisations_median_rms_nm", [0]))
    budget_lines = []
    if budget:
        budget_lines = ["| controller | perfect sensor | SH | SH + photon noise | temporal | aliasing | noise |",
                        "|---|---|---|---|---|---|---|"]
        for name, b in budget["controllers"].items():
            budget_lines.append(f"| {name} | {b['residual_perfect_sensor_nm']:.1f} | {b['residual_shack_hartmann_nm']:.1f} "
                                f"| {b['residual_photon_noise_nm']:.1f} | {b['temporal_nm']:.1f} | "
                                f"{b['aliasing_nm']:.1f} | {b['noise_nm']:.1f} |")
        budget_lines.append(f"\nFitting error {budget['fitting_error_nm']:.1f} nm; the other terms split the residual "
                            "in quadrature (temporal: perfect sensor less fitting; aliasing: SH less perfect sensor; "
                            "noise: photon noise less SH).")
    return f"""## 6. eofnn's controllers inside other simulators (OOPAO, HCIPy)

`bash experiments/interop/run.sh` (`docs/interop.md`): each simulator's own closed loop (1 kHz, two-frame delay,
a DM applying 2x the command, one 20 m/s layer) records telemetry with its integrator and a dither; eofnn
identifies the plant from it, fits closed-loop EOF from that telemetry alone (one refit on telemetry the EOF
recorded itself), replays it on a held-out realisation, and runs it (the exported `eofnn.runtime` filter) in the
simulator's loop against the best-gain integrator of a scan in that loop. Beside them runs the *split* controller:
the integrator (its chosen gain) keeps the `L` lowest-order modes of the recorded pseudo-open loop (its principal
components), and on the other modes the EOF's command is mixed in with a share `mix` (`SplitControl`). Each
contender is tuned on data it is not scored on: the EOF's ridge alpha on validation frames; the integrator's gain
on a realisation of its own (6-7 gains, the scan climbing past the top of its grid while that is best); the
split's `(L, mix)` on that same realisation (3 x 3: `L` in 0, K / 64, K / 16; mix 0.25, 0.5, 1). All are then
scored on the same {n_scored} further realisations: the mean of their median residual OPD (nm), each realisation in
brackets. With a Shack-Hartmann the telemetry sees the DM gain times the sensor's optical gain, which the adapter
measures with probes (the target in brackets).

| system | DM gain identified (target) | replay: EOF / integrator | in loop: integrator | EOF | split | tuned on scan |
|---|---|---|---|---|---|---|
{chr(10).join(rows)}

**Where the residual goes** (OOPAO, 20 x 20 on 4 m, the first scored realisation; the same loop with a perfect
sensor, the Shack-Hartmann without noise and with photon noise):

{chr(10).join(budget_lines) if budget_lines else '(not run)'}

- The EOF halves the temporal error and cannot remove aliasing or noise: it predicts the *measured* residual,
  aliasing included, so its replay gain (which scores the measurement) does not carry to the true OPD. With a
  perfect sensor and in HCIPy (phase projection, no aliasing) it beats the best-gain integrator in the loop; with
  OOPAO's Shack-Hartmann it does not{_eof_diverged(sh_runs)}.
{_split_finding(big_runs, small_runs)}
- The reconstructor keeps the interaction matrix's singular values above `rcond` times the largest: 0.15 up to
  20 x 20 and {big['rcond']:g} at 40 x 40 ({big['n_seen_modes']} of {big['n_actuators']} modes), because a zonal
  Shack-Hartmann's smooth modes have the smallest singular values and their share of the spectrum shrinks as
  1 / n (at 0.15 the 40 x 40 loop dropped smooth modes that neither controller could then correct).
- *Limits*: {n_scored} scored realisations per system, 500-900 scored frames each (0.5-0.9 s of turbulence); the
  split's grid has 9 points against the integrator's 6-7 gains and does not climb past its edge (mix 0.25, its
  lowest, was chosen at 40 x 40); 1600-2000 frames per recording; one wind (20 m/s, one layer).
"""
