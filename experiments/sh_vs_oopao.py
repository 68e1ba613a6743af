"""eofnn's Shack-Hartmann loop against OOPAO's on the same system (issue 29): writes summary.json and results.md.

    .venv/bin/python experiments/sh_vs_oopao.py --out experiments/runs/sh_vs_oopao      # 20 x 20 on 8 m
    .venv/bin/python experiments/sh_vs_oopao.py --n-subapertures 10 --diameter 4 --out experiments/runs/sh_vs_oopao_10

What is built and measured: eofnn/studies/sh_compare.py (and sh_system.py, sh_diagnostics.py). Each number is the
mean over the scored realisations, with their standard deviation; "agree" is |OOPAO / eofnn - 1| <= 20%.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TOLERANCE = 0.2


def _cell(values) -> str:
    finite = [v for v in values if v is not None]
    if not finite or len(finite) < len(values):
        return "diverged"
    mean = sum(finite) / len(finite)
    if len(finite) == 1:
        return f"{mean:.1f}"
    std = (sum((v - mean) ** 2 for v in finite) / (len(finite) - 1)) ** 0.5
    return f"{mean:.1f} ± {std:.1f}"


def _mean(values):
    finite = [v for v in values if v is not None]
    return None if not finite or len(finite) < len(values) else sum(finite) / len(finite)


def _row(name: str, eofnn, oopao, *extra) -> str:
    a, b = _mean(eofnn), _mean(oopao)
    ratio = "" if a in (None, 0) or b is None else f"{b / a:.2f}"
    agree = "" if not ratio else ("yes" if abs(b / a - 1) <= TOLERANCE else "**no**")
    return "| " + " | ".join([name, _cell(eofnn), _cell(oopao), ratio, agree,
                              *(e if isinstance(e, str) else _cell(e) for e in extra)]) + " |"


def table(out: dict) -> str:
    """The markdown page of one comparison."""
    s, m = out["system"], out["mapping"]
    lines = [f"# eofnn's Shack-Hartmann against OOPAO's: {s['n_subapertures']} x {s['n_subapertures']} on "
             f"{s['diameter_m']:g} m",
             "",
             f"r0 = {s['r0_m']:g} m at 500 nm, L0 = {s['outer_scale_m']:g} m, one layer at {s['wind_speed_mps']:g} m/s, "
             f"{s['frame_rate_hz']:g} Hz, {s['delay_frames']}-frame delay, I band, integrator "
             f"`y(n) = y(n-1) - g wfs(n-{s['delay_frames']})`; {out['config']['realisations']} realisations of "
             f"{out['config']['frames']} frames, scored after {out['config']['settle_frames']} (mean ± std over "
             "realisations of each run's median residual RMS over the pupil, piston removed).",
             "",
             f"Mapping: pitch d = {m['pitch_m']:g} m in both. OOPAO: pupil {m['oopao']['pupil_m']:g} m, "
             f"{m['oopao']['actuators']} actuators, {m['oopao']['subapertures']} subapertures (half lit or more), "
             f"{m['oopao']['seen_modes']} modes controlled (rcond {m['oopao']['rcond']:g}), "
             f"{m['oopao']['sh_pixels']} x {m['oopao']['sh_pixels']} pixels of lambda/d per subaperture. eofnn: "
             f"grid of {m['eofnn']['grid_n_across']} across on {m['eofnn']['pupil_m']:g} m (its pupil), "
             f"{m['eofnn']['actuators']} actuators, {m['eofnn']['subapertures']} subapertures, "
             f"{m['eofnn']['seen_modes']} modes controlled (cut {m['eofnn']['relative_cut']:g}).",
             "",
             "| quantity (nm) | eofnn | OOPAO | OOPAO / eofnn | within 20% | OOPAO on eofnn's turbulence | "
             "eofnn over OOPAO's pupil | eofnn with OOPAO's slope noise |",
             "|---|---|---|---|---|---|---|---|"]
    for mag, entry in out["magnitudes"].items():
        e, o, t = entry["eofnn"], entry["oopao"], entry.get("oopao_on_eofnn_turbulence")
        first = mag == next(iter(out["magnitudes"]))
        gains = f"(gains: eofnn {e['gain']:g}, OOPAO {o['gain']:g})"
        names = [("fitting", "fitting error"), ("aliasing", f"aliasing, I = {mag} {gains}"),
                 ("noise", f"noise, I = {mag}"), ("temporal", f"temporal, I = {mag}")]
        for key, name in names:
            if key == "fitting" and not first:
                continue
            lines.append(_row(name, e["terms"][key], o["terms"][key], t["terms"][key] if t else "",
                              e["inner_terms"][key], e["matched_noise"]["noise"] if key == "noise" else ""))
        lines.append(_row(f"**best-gain integrator, I = {mag}**", e["runs"]["none"], o["runs"]["none"],
                          t["runs"]["none"] if t else "", e["runs"]["inner:none"], e["matched_noise"]["none"]))
    lines += ["", "Where the two sensors differ:", "",
              "| | eofnn | OOPAO |", "|---|---|---|"]
    for mag, entry in out["magnitudes"].items():
        e, o = entry["eofnn"], entry["oopao"]
        noise = o["slope_noise"]
        lines += [f"| photons per subaperture and frame, I = {mag} | {e['photons_per_subaperture']:.0f} | "
                  f"{noise['photons_per_subaperture']:.0f} |",
                  f"| noise per slope (nm across a subaperture), I = {mag}: fully lit, flat / in the loop / every "
                  f"slope in the loop | {e['slope_noise_nm']:.1f} (Rousset, Gaussian spot) | {noise['flat_nm']:.1f} / "
                  f"{noise['loop_nm']:.1f} / {noise['loop_all_nm']:.1f} |",
                  f"| open-loop noise on the DM over the pupil (R n), I = {mag}: flat wavefront / in the loop | "
                  f"{e['open_loop_pupil_nm']:.1f} | {noise['flat_pupil_nm']:.1f} / {noise['loop_pupil_nm']:.1f} |",
                  f"| optical gain in the loop (push-pull probes), I = {mag}, gain {o['gain']:g} | 1 | "
                  f"{o['optical_gain']['mean']:.3f} ± {o['optical_gain']['se']:.3f} |",
                  f"| spot FWHM (lambda/d) giving eofnn OOPAO's in-loop noise on the DM, I = {mag} | "
                  f"{e['matched_noise']['spot_fwhm_lambda_over_d']:.2f} | |"]
        if "geometric_aliasing" in o:
            lines.append(f"| aliasing of OOPAO's geometric SH (its diffractive SH: above), gain {o['gain']:g} | | "
                         f"{_cell(o['geometric_aliasing'])} |")
    first = next(iter(out["magnitudes"].values()))
    same = first.get("oopao_on_eofnn_turbulence")
    lines.append(f"| fitting error with the DM fitted over OOPAO's pupil alone (OOPAO: on eofnn's turbulence, if run) | "
                 f"{_cell(first['eofnn']['fit_over_oopao_pupil'])} | {_cell(same['terms']['fitting']) if same else ''} |")
    lines.append(f"| noise on the pupil per nm of white slope noise (reconstructor) | "
                 f"{out['noise_propagation']['eofnn']:.3f} | {out['noise_propagation']['oopao']:.3f} |")
    sf = out["structure_function"]
    for lag, a, b, vk in zip(sf["lags_m"], sf["eofnn_nm2"], sf["oopao_nm2"], sf["von_karman_nm2"], strict=True):
        lines.append(f"| phase structure function at {lag:.2f} m, / von Karman's | {a / vk:.2f} | {b / vk:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    from eofnn.studies.sh_compare import CompareConfig, compare
    from eofnn.studies.sh_system import ShSystem

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n-subapertures", type=int, default=20)
    p.add_argument("--diameter", type=float, default=8.0)
    p.add_argument("--r0", type=float, default=0.15, help="m at 500 nm")
    p.add_argument("--wind", type=float, default=10.0, help="m/s")
    p.add_argument("--magnitudes", type=float, nargs="+", default=[8.0, 10.0], help="I band")
    p.add_argument("--frames", type=int, default=1000)
    p.add_argument("--settle", type=int, default=200)
    p.add_argument("--realisations", type=int, default=3)
    p.add_argument("--gains", type=float, nargs="+", default=[0.3, 0.4, 0.5, 0.6])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--samples-per-subaperture", type=int, default=4,
                   help="OOPAO's pupil pixels (and SH pixels) per subaperture; eofnn's fine intervals")
    p.add_argument("--no-eofnn-turbulence", action="store_true", help="skip OOPAO's sensor on eofnn's turbulence")
    p.add_argument("--no-geometric", action="store_true", help="skip OOPAO's geometric SH")
    p.add_argument("--out", default="experiments/runs/sh_vs_oopao")
    a = p.parse_args(argv)
    system = ShSystem(a.n_subapertures, a.diameter, a.r0, wind_speed_mps=a.wind,
                      samples_per_subaperture=a.samples_per_subaperture)
    config = CompareConfig(tuple(a.magnitudes), a.frames, a.settle, a.realisations, tuple(a.gains), a.seed,
                           not a.no_eofnn_turbulence, not a.no_geometric)
    start = time.time()
    out = compare(system, config, log=lambda msg: print(f"[{time.time() - start:6.0f} s] {msg}", flush=True))
    out["seconds"] = time.time() - start
    folder = Path(a.out)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "summary.json").write_text(json.dumps(out, indent=1, default=float) + "\n")
    page = table(out) + f"\n`{' '.join(['python', 'experiments/sh_vs_oopao.py', *(argv or sys.argv[1:])])}` " \
                        f"({out['seconds'] / 60:.0f} min)\n"
    (folder / "results.md").write_text(page)
    print(page)


if __name__ == "__main__":
    main()
