"""Sections of experiments/README.md on scale and on other simulators: the ELT-class loop (experiments/elt_small)."""

from __future__ import annotations

from report_common import NAMES, cell, load, margin

NAMES_ELT = {**NAMES, "cl_eof_nb": "closed-loop EOF, neighbourhood"}


def _tuning(result: dict, name: str) -> str:
    gains = result.get("integrator_gains", {}).get("nominal", {}).get(name)
    if gains:
        return f"gain {gains['gain']:.3g}"
    alpha = result.get("ridge_alphas", {}).get("nominal", {}).get(name)
    return f"α {alpha['alpha']:.2g}" if alpha else ""


def elt_section() -> str:
    result = load("elt_small/metrics.json")
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

`eofnn compare --config configs/elt_small.yaml --out experiments/elt_small`: `configs/elt.yaml`'s 39 m telescope,
80 actuators across (5024 active, pitch 0.49 m), three layers of exact frozen flow blowing at 30, 150 and 260
degrees (8, 12 and 20 m/s), seen through each subaperture, 1 nm of WFS noise, 1 kHz, two-frame delay. Every
predictor learns as an observatory would, from telemetry alone (2000 frames of dithered-integrator telemetry, the
plant identified from the dither, 500 validation frames for `alpha: auto`); the integrator's gain is a refined scan
on a stream of its own. Median RMS over {first['n_frames'] - first['settle_frames']} settled frames of one test stream;
time and peak resident memory of the process after each step (each step builds its own streams; the turbulence
screens are shared between steps):

{chr(10).join(lines)}

- The neighbourhood filters' coupled stability analysis is refused at this size (its companion matrix exceeds
  12000 rows; `eofnn.analysis.block`); their DM-gain interval can be measured by simulation
  (`--simulated_margins`), which this short run does not do.
- *Limits*: short telemetry (2000 frames) and test stream; one realisation; the full comparison
  (`configs/elt_scao.yaml`: 10000 training frames, a 2x DM-gain scenario, simulated margins) has not been run.
"""
