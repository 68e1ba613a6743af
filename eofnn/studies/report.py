"""Error budgets, the small outputs (``metrics.json``, ``results.md``) and the shared options of the interop
examples."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from eofnn.outputs import write_text_atomic


def example_parser(description: str) -> argparse.ArgumentParser:
    """The options every interop example takes (the system, the DM's gain, the wind, the frames, the output
    folder); ``--small`` is applied by :func:`parse_example`."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--small", action="store_true", help="10 x 10 subapertures on 2 m, short runs (CI)")
    parser.add_argument("--n-subapertures", type=int, default=40)
    parser.add_argument("--diameter", type=float, default=8.0, help="m")
    parser.add_argument("--dm-gain", type=float, default=2.0)
    parser.add_argument("--wind", type=float, default=20.0, help="m/s")
    parser.add_argument("--frames", type=int, default=3000, help="frames of telemetry per recording")
    parser.add_argument("--realisations", type=int, default=1,
                        help="turbulence realisations every contender is scored on (after tuning on another)")
    parser.add_argument("--out", type=Path, help="folder for metrics.json and results.md")
    return parser


def parse_example(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """``argv`` parsed; ``--small`` sets 10 x 10 subapertures on 2 m."""
    args = parser.parse_args(argv)
    if args.small:
        args.n_subapertures, args.diameter = 10, 2.0
    return args


def quadrature_difference(a: float, b: float) -> float:
    """``sign(a² - b²) sqrt(|a² - b²|)``: the part of ``a`` that ``b`` lacks, for independent errors (nm)."""
    d = a * a - b * b
    return math.copysign(math.sqrt(abs(d)), d)


def aliasing_budget(perfect: dict, shack_hartmann: dict, photon_noise: dict) -> dict:
    """What limits each controller, from three runs of :func:`eofnn.studies.study.run_study` (``summary()`` with a
    ``fitting_error``): a perfect (non-aliasing, noise-free) sensor, the Shack-Hartmann noise-free, and with photon
    noise. Residual OPD medians (nm) split in quadrature: fitting error (the DM cannot make it), temporal (what is
    left with a perfect sensor: servo lag, which prediction attacks), aliasing (SH minus perfect) and noise (photon
    noise minus noise-free), per controller (the split one too where every run has it); ``eof_removes_nm``:
    integrator minus EOF in quadrature, per sensor. Quadrature
    differences assume independent terms; a negative one means the term helped (printed with its sign)."""
    fit = perfect["fitting_error"]["median_rms_nm"]
    out = {"fitting_error_nm": fit, "controllers": {}, "eof_removes_nm": {}}
    runs = (perfect, shack_hartmann, photon_noise)
    split = all((run.get("split") or {}).get("median_rms_nm") is not None for run in runs)
    for name in ("integrator", "eof", "split") if split else ("integrator", "eof"):
        p, s, n = (run[name]["median_rms_nm"] for run in runs)
        out["controllers"][name] = {
            "residual_perfect_sensor_nm": p, "residual_shack_hartmann_nm": s, "residual_photon_noise_nm": n,
            "temporal_nm": quadrature_difference(p, fit), "aliasing_nm": quadrature_difference(s, p),
            "noise_nm": quadrature_difference(n, s)}
    for label, run in (("perfect_sensor", perfect), ("shack_hartmann", shack_hartmann),
                       ("photon_noise", photon_noise)):
        out["eof_removes_nm"][label] = quadrature_difference(run["integrator"]["median_rms_nm"],
                                                             run["eof"]["median_rms_nm"])
    return out


def _nm(value: float | None) -> str:
    """A median RMS in the table, or ``diverged`` where the loop did not hold."""
    return "diverged" if value is None else f"{value:.2f}"


def split_text(split: dict | None) -> str:
    """The split controller's median RMS and the modes it left to the integrator, or why there is none."""
    if not split:
        return "not run"
    if split["integrated_modes"] is None:
        return "every split diverged"
    return f"{_nm(split['median_rms_nm'])} nm ({split['integrated_modes']} modes integrated, mix {split['mix']:g})"


def write_results(folder: str | Path, simulator: str, metrics: dict, command: str) -> Path:
    """``folder/metrics.json`` (everything) and ``folder/results.md`` (the table), replacing earlier ones."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    metrics = {"command": command, **metrics}
    write_text_atomic(folder / "metrics.json", json.dumps(metrics, indent=1))
    lines = [f"# eofnn inside {simulator}", "", f"`{command}`", "",
             "| run | DM gain identified (DM gain x sensor optical gain) | replay EOF / integrator (nm) "
             "| in-loop EOF / best integrator (nm, gain) | in-loop split (nm, modes integrated) | fitting error (nm) |",
             "|---|---|---|---|---|---|"]
    for name, run in metrics["runs"].items():
        ident, rep, integ = run["identified"], run["replay"], run["integrator"]
        truth = ident.get("dm_gain_times_optical_gain", ident.get("dm_gain_true"))
        fit = run.get("fitting_error", {}).get("median_rms_nm")
        lines.append(f"| {name} | {ident['dm_gain']:.4f} ({truth:.4f}) | {rep['predictor_median_rms_nm']:.2f} / "
                     f"{rep['integrator_median_rms_nm']:.2f} | {_nm(run['eof']['median_rms_nm'])} / "
                     f"{_nm(integ['median_rms_nm'])} ({integ['best_gain']}) | {split_text(run.get('split'))} | "
                     f"{'' if fit is None else f'{fit:.2f}'} |")
    if "budget" in metrics:
        b = metrics["budget"]
        lines += ["", f"Error budget (median residual OPD, nm, split in quadrature; fitting error "
                      f"{b['fitting_error_nm']:.2f} nm):", "",
                  "| controller | perfect sensor | SH | SH + photon noise | temporal | aliasing | noise |",
                  "|---|---|---|---|---|---|---|"]
        for name, c in b["controllers"].items():
            lines.append(f"| {name} | {c['residual_perfect_sensor_nm']:.2f} | {c['residual_shack_hartmann_nm']:.2f} | "
                         f"{c['residual_photon_noise_nm']:.2f} | {c['temporal_nm']:.2f} | {c['aliasing_nm']:.2f} | "
                         f"{c['noise_nm']:.2f} |")
        removed = ", ".join(f"{k} {v:.2f} nm" for k, v in b["eof_removes_nm"].items())
        lines += ["", f"The EOF removes (integrator minus EOF, in quadrature): {removed}."]
    write_text_atomic(folder / "results.md", "\n".join(lines) + "\n")
    return folder


def psd_bands(metrics: dict, name: str) -> tuple[float, float] | None:
    """The variance of ``name``'s measured residual (nm², the loop's command units, per actuator) below and above
    the frozen-flow frequency ``v / (2 pitch)``, from its temporal PSD; None where it has none."""
    power = metrics["contenders"][name].get("measured_psd_nm2_per_hz")
    if not power or "psd_frequency_hz" not in metrics:
        return None
    freq, power = np.asarray(metrics["psd_frequency_hz"]), np.asarray(power)
    df, low = freq[1] - freq[0], freq < metrics["frozen_flow_hz"]
    return float(power[low].sum() * df), float(power[~low].sum() * df)


def psd_bands_markdown(metrics: dict) -> list[str]:
    """The lines of ``results.md`` that read the temporal PSDs: each contender's measured residual split at the
    frozen-flow frequency (what prediction acts on, below; noise and aliasing passed back, above)."""
    bands = {name: psd_bands(metrics, name) for name in metrics["contenders"]}
    if not any(bands.values()):
        return []
    fc = metrics["frozen_flow_hz"]
    lines = ["", f"Temporal PSD of the measured residual (per actuator, the loop's command units; `psd.png`), "
                 f"integrated below and above v / (2 pitch) = {fc:.0f} Hz:", "",
             f"| contender | below {fc:.0f} Hz (nm²) | above {fc:.0f} Hz (nm²) |", "|---|---|---|"]
    for name, band in bands.items():
        lines.append(f"| {name} | " + (" | ".join(f"{v:.0f}" for v in band) if band else "diverged | ") + " |")
    return lines
