"""eofnn's pyramid loop against OOPAO's on one system built alike (:mod:`eofnn.studies.pyramid_compare`):
``experiments/pyramid/vs_oopao.py --loop`` runs it.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python experiments/pyramid/vs_oopao.py --loop \\
        --out experiments/pyramid/vs_oopao/summary.json --md experiments/pyramid/vs_oopao.md

Goals (the project's pyramid issue): the response per mode within 10%, the optical gains within 15%, the best-gain
integrators' residuals within 20%.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from eofnn.studies.pyramid_compare import PyramidSystem, compare  # noqa: E402

GOALS = {"response": 0.10, "optical_gains": 0.15, "residual": 0.20}


def loop_main(argv) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-subapertures", type=int, default=16, help="detector pixels across a pupil image")
    parser.add_argument("--diameter", type=float, default=4.0, help="m")
    parser.add_argument("--samples-per-pixel", type=int, default=2)
    parser.add_argument("--modulation", type=float, default=3.0, help="lambda/D (OOPAO's radius)")
    parser.add_argument("--r0", type=float, default=0.15, help="m at 500 nm")
    parser.add_argument("--wind", type=float, default=10.0, help="m/s")
    parser.add_argument("--relative-cut", type=float, default=0.1)
    parser.add_argument("--gains", type=float, nargs="+", default=[0.3, 0.4, 0.5, 0.6, 0.7])
    parser.add_argument("--frames", type=int, default=1500)
    parser.add_argument("--settle", type=int, default=300)
    parser.add_argument("--realisations", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--modes", type=int, default=100, help="KL modes of the response comparison")
    parser.add_argument("--gain-modes", type=int, default=50, help="KL modes of the optical gains")
    parser.add_argument("--probe-frames", type=int, default=6, help="settled frames whose residual is probed")
    parser.add_argument("--out", type=Path, default=None, help="every number (JSON)")
    parser.add_argument("--md", type=Path, default=None, help="the table (markdown)")
    args = parser.parse_args(argv)
    system = PyramidSystem(args.n_subapertures, args.diameter, args.samples_per_pixel, args.modulation, args.r0,
                           wind_speed_mps=args.wind, relative_cut=args.relative_cut)
    out = compare(system, args.gains, args.frames, args.settle, args.realisations, args.seed, args.modes,
                  args.gain_modes, args.probe_frames, progress=lambda text: print(text, flush=True))
    out["command"] = " ".join(["python experiments/pyramid/vs_oopao.py --loop", *argv])
    out["summary"] = summary(out)
    text = markdown(out)
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1) + "\n")
    if args.md is not None:
        args.md.write_text(text)
    return out


def summary(out: dict) -> dict:
    """The agreement against each goal."""
    ratio = np.asarray(out["response"]["ratio"])
    same_dm = np.asarray(out["response"]["ratio_with_oopaos_dm"])
    og = {k: np.asarray(v) for k, v in out["optical_gains"].items() if k.endswith("_loop")}
    own = og["eofnn_sensor_eofnn_loop"] / og["oopao_sensor_oopao_loop"]
    same_residual = og["eofnn_sensor_oopao_loop"] / og["oopao_sensor_oopao_loop"]
    best = out["integrator"]["best"]
    residual = best["eofnn"]["median_rms_nm"] / best["oopao"]["median_rms_nm"]
    fit = out["integrator"]["fitting_error_nm"]
    return {
        "response_ratio_median": float(np.median(ratio)), "response_ratio_range": [float(ratio.min()), float(ratio.max())],
        "response_modes_within_goal": int((np.abs(ratio - 1) <= GOALS["response"]).sum()), "response_modes": len(ratio),
        "response_with_oopaos_dm_range": [float(same_dm.min()), float(same_dm.max())],
        "optical_gain_mean": {k: float(v.mean()) for k, v in og.items()},
        "optical_gain_ratio_own_loops_range": [float(own.min()), float(own.max())],
        "optical_gain_ratio_own_loops_median": float(np.median(own)),
        "optical_gain_ratio_same_residual_range": [float(same_residual.min()), float(same_residual.max())],
        "optical_gain_ratio_eofnn_probe_over_oopao_gsc_range": [
            float((v := og["eofnn_sensor_eofnn_loop"] / og["oopao_gain_sensing_camera_oopao_loop"]).min()),
            float(v.max())],
        "residual_ratio": float(residual),
        "fitting_error_ratio": fit["eofnn"] / fit["oopao"],
        "goals_met": {"response": bool(np.abs(ratio - 1).max() <= GOALS["response"]),
                      "optical_gains": bool(np.abs(own - 1).max() <= GOALS["optical_gains"]),
                      "residual": bool(abs(residual - 1) <= GOALS["residual"])}}


def markdown(out: dict) -> str:
    s, sm, og = out["system"], out["summary"], out["optical_gains"]
    best, fit = out["integrator"]["best"], out["integrator"]["fitting_error_nm"]
    means = sm["optical_gain_mean"]

    def yes(goal):
        return "met" if sm["goals_met"][goal] else "**missed**"

    lines = [
        "# eofnn's pyramid loop against OOPAO's (experiments/pyramid/vs_oopao.py --loop)", "",
        f"`{out['command']}`", "",
        f"System: {s['n_subapertures']} x {s['n_subapertures']} pixels per pupil image, {s['pupil_points']} pupil points "
        f"across {s['diameter_m']:g} m, Fried DM of {s['actuators']} actuators, modulation {s['modulation_lambda_over_d']:g} "
        f"lambda/D ({s['modulation_points']} points; eofnn {s['eofnn_modulation_lambda_over_d']:.4f}, OOPAO's effective "
        f"radius), I band, slopes maps, noise-free, relative cut {s['relative_cut']:g} (kept modes eofnn "
        f"{s['kept_modes']['eofnn']}, OOPAO {s['kept_modes']['oopao']}), r0 {s['r0_m']:g} m at 500 nm, L0 "
        f"{s['outer_scale_m']:g} m, one layer at {s['wind_speed_mps']:g} m/s (eofnn's exact frozen flow in both), "
        f"{s['frame_rate_hz']:g} Hz, {s['delay_frames']} frames of delay; {out['realisations']} realisations of "
        f"{out['frames']} frames ({out['settle_frames']} settling); valid pixels eofnn "
        f"{out['response']['valid_pixels']['eofnn']}, OOPAO {out['response']['valid_pixels']['oopao']}.", "",
        "| measured | eofnn | OOPAO | eofnn / OOPAO | goal |", "|---|---|---|---|---|",
        f"| interaction matrix, response per KL mode (first {sm['response_modes']}) | | | median "
        f"{sm['response_ratio_median']:.3f}, range {sm['response_ratio_range'][0]:.3f}-{sm['response_ratio_range'][1]:.3f} "
        f"({sm['response_modes_within_goal']} of {sm['response_modes']} within 10%) | 10%: {yes('response')} |",
        f"| the same, eofnn's pyramid given OOPAO's DM surfaces | | | range {sm['response_with_oopaos_dm_range'][0]:.4f}-"
        f"{sm['response_with_oopaos_dm_range'][1]:.4f} | |",
        f"| optical gains of the first {og['modes']} KL modes about each best-gain loop's own residual ({og['residuals']} "
        f"residuals; mean over modes) | {means['eofnn_sensor_eofnn_loop']:.3f} | {means['oopao_sensor_oopao_loop']:.3f} | "
        f"per mode {sm['optical_gain_ratio_own_loops_range'][0]:.3f}-{sm['optical_gain_ratio_own_loops_range'][1]:.3f} "
        f"(median {sm['optical_gain_ratio_own_loops_median']:.3f}) | 15%: {yes('optical_gains')} |",
        f"| the same, both sensors about OOPAO's residuals | {means['eofnn_sensor_oopao_loop']:.3f} | "
        f"{means['oopao_sensor_oopao_loop']:.3f} | per mode {sm['optical_gain_ratio_same_residual_range'][0]:.3f}-"
        f"{sm['optical_gain_ratio_same_residual_range'][1]:.3f} | |",
        f"| OOPAO's GainSensingCamera about OOPAO's residuals (eofnn: its probe about its own) | "
        f"{means['eofnn_sensor_eofnn_loop']:.3f} | {means['oopao_gain_sensing_camera_oopao_loop']:.3f} | per mode "
        f"{sm['optical_gain_ratio_eofnn_probe_over_oopao_gsc_range'][0]:.3f}-"
        f"{sm['optical_gain_ratio_eofnn_probe_over_oopao_gsc_range'][1]:.3f} | |",
        f"| residual RMS of the probed frames (nm) | {og['residual_rms_nm']['eofnn_loop']:.1f} | "
        f"{og['residual_rms_nm']['oopao_loop']:.1f} | | |",
        f"| best-gain integrator, median residual over the pupil (nm; gain) | {best['eofnn']['median_rms_nm']:.1f} "
        f"({best['eofnn']['gain']:g}) | {best['oopao']['median_rms_nm']:.1f} ({best['oopao']['gain']:g}) | "
        f"{sm['residual_ratio']:.3f} | 20%: {yes('residual')} |",
        f"| fitting error (nm) | {fit['eofnn']:.1f} | {fit['oopao']:.1f} | {sm['fitting_error_ratio']:.3f} | |", "",
        "Integrator scan (median residual, nm): " + "; ".join(
            f"{code} " + ", ".join(f"{g}: {'diverged' if v is None else f'{v:.1f}'}" for g, v in scan.items())
            for code, scan in out["integrator"]["scan"].items()), ""]
    return "\n".join(lines)
