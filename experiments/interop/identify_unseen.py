"""``eofnn twin`` on OOPAO recordings at conditions never used while developing it (issue 46's must-show): two-layer
records (speeds 5 m/s or more apart, different directions) and one-layer records at other speeds, directions, r0 and
noise levels than examples/twin_accuracy.py's O1-O3 and the eofnn cases A-F.

Each case: OOPAO's geometric Shack-Hartmann, 4 m, 20 x 20 subapertures (357 actuators of its Fried DM), OOPAO's own
von Karman atmosphere with the case's layers (L0 25 m, r0 at 500 nm), white slope noise of the stated RMS per actuator
(OOPAO's command units; x 2.99 in eofnn's) added to the slopes, a dithered integrator (gain 0.4, 10 nm), 4000 frames
at 1 kHz, delay 2. Written as a real-time computer writes it (y, wfs = R @ slopes, positions, delay, frame rate) with
OOPAO's interaction matrix and reconstructor beside it; ``eofnn twin --command_unit peak`` sees nothing else. OOPAO's
wind direction ``a`` moves the turbulence along ``90 - a`` degrees of its DM's positions.

The cases and their seeds below were fixed before the first run of this script; nothing in eofnn was changed after
seeing its results (see results.md). Targets: r0 and wind speed within 10%, direction within 10 deg, noise within
20%, the right layer count.

    OMP_NUM_THREADS=1 .venv/bin/python experiments/interop/identify_unseen.py            # all cases
    OMP_NUM_THREADS=1 .venv/bin/python experiments/interop/identify_unseen.py U1 U4      # some
    OMP_NUM_THREADS=1 .venv/bin/python experiments/interop/identify_unseen.py page       # results.md again

Raw records and twins go to experiments/runs/interop/identify_unseen/; the summary (summary.json, results.md) to
experiments/interop/identify_unseen/.
"""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
RUNS = ROOT / "experiments" / "runs" / "interop" / "identify_unseen"
SUMMARY = ROOT / "experiments" / "interop" / "identify_unseen"
FRAMES = 4000
OOPAO_L0_M = 25.0

# Fixed before the first run. layers: (speed m/s, OOPAO direction deg, Cn2 fraction, altitude m); noise: slope noise
# per actuator, nm of OOPAO's commands (O1-O3 used 25 nm, r0 0.10-0.16 m, 8-18 m/s at 0-45 deg, seeds 21-23).
CASES = {
    "U1": {"r0": 0.14, "layers": [(8.0, 100.0, 0.6, 0.0), (18.0, 220.0, 0.4, 4000.0)], "noise": 25.0, "seed": 101},
    "U2": {"r0": 0.11, "layers": [(6.0, -30.0, 0.5, 0.0), (15.0, 150.0, 0.5, 6000.0)], "noise": 15.0, "seed": 102},
    "U3": {"r0": 0.18, "layers": [(10.0, 60.0, 0.7, 0.0), (22.0, 300.0, 0.3, 8000.0)], "noise": 35.0, "seed": 103},
    "U4": {"r0": 0.09, "layers": [(25.0, 200.0, 1.0, 0.0)], "noise": 20.0, "seed": 104},
    "U5": {"r0": 0.20, "layers": [(5.0, 135.0, 1.0, 0.0)], "noise": 40.0, "seed": 105},
    # Added for the spectral noise estimator (fixed and committed before their first run, ident46b): fast wind and
    # low noise, where the lagged-structure estimator failed on U2 and U4.
    "U6": {"r0": 0.13, "layers": [(7.0, 20.0, 0.55, 0.0), (19.0, 250.0, 0.45, 5000.0)], "noise": 22.0, "seed": 106},
    "U7": {"r0": 0.08, "layers": [(30.0, 310.0, 1.0, 0.0)], "noise": 28.0, "seed": 107},
    "U8": {"r0": 0.16, "layers": [(12.0, 170.0, 1.0, 0.0)], "noise": 12.0, "seed": 108},
    "U9": {"r0": 0.18, "layers": [(21.0, 80.0, 1.0, 0.0)], "noise": 18.0, "seed": 109},
    # Added for the references projected on the record's reconstructor's modes (r0bias46, found on U9's conditions
    # and O1-O3): fixed and committed before their first run; U1-U9 are no longer unseen for r0.
    "U10": {"r0": 0.12, "layers": [(15.0, 45.0, 1.0, 0.0)], "noise": 30.0, "seed": 110},
    "U11": {"r0": 0.17, "layers": [(9.0, 200.0, 0.6, 0.0), (24.0, 340.0, 0.4, 7000.0)], "noise": 20.0, "seed": 111},
    "U12": {"r0": 0.10, "layers": [(8.0, 260.0, 1.0, 0.0)], "noise": 10.0, "seed": 112},
    "U13": {"r0": 0.15, "layers": [(12.0, 100.0, 0.5, 0.0), (27.0, 10.0, 0.5, 9000.0)], "noise": 25.0, "seed": 113},
    "U14": {"r0": 0.22, "layers": [(18.0, 170.0, 1.0, 0.0)], "noise": 35.0, "seed": 114},
}
#: The code the summary's current table is of; a run under another moves the table to ``earlier`` first.
CODE = ("r0bias46: the twin's reference turbulence projected on the modes the record's reconstructor outputs "
        "(U10-U14 unseen; U1-U9 seen while finding the change)")
TARGETS = {"r0_rel": 0.10, "speed_rel": 0.10, "direction_deg": 10.0, "noise_rel": 0.20}


def _multilayer_loop(case: dict):
    """OOPAO's loop (eofnn.interop.oopao.OopaoLoop) with the case's layers in place of its single one."""
    from eofnn.interop.oopao import OopaoLoop, quiet

    class MultiLayerLoop(OopaoLoop):
        def _build(self, Atmosphere, *rest) -> None:
            super()._build(Atmosphere, *rest)
            speeds, directions, fractions, altitudes = (list(map(float, col)) for col in zip(*case["layers"],
                                                                                                  strict=True))
            with quiet():
                self.atm = Atmosphere(telescope=self.tel, r0=case["r0"], L0=OOPAO_L0_M, windSpeed=speeds,
                                      fractionalR0=fractions, windDirection=directions, altitude=altitudes)
                self.atm.initializeAtmosphere(self.tel)

    first = case["layers"][0]
    return MultiLayerLoop(n_subapertures=20, diameter_m=4.0, sensor="geometric", r0_m=case["r0"],
                          outer_scale_m=OOPAO_L0_M, wind_speed_mps=first[0], wind_direction_deg=first[1], rcond=0.15)


def record(name: str) -> tuple[Path, dict, list[str]]:
    """The case's telemetry (cached), its truth in eofnn's units and directions, and the twin's options."""
    from eofnn.interop.loop import IntegratorControl, run_closed_loop, with_slope_noise
    from eofnn.sim.sensing.least_squares import MECHANICAL_COUPLING, surface_per_command

    case = CASES[name]
    path, im, r = RUNS / f"{name}.npz", RUNS / f"{name}_im.npy", RUNS / f"{name}_r.npy"
    if not path.exists():
        sim = _multilayer_loop(case)
        reconstructor = sim.reconstructor
        with_slope_noise(sim, case["noise"], case["seed"] + 1000)
        rec = run_closed_loop(sim, IntegratorControl(0.4, dither_nm=10.0, seed=case["seed"]), FRAMES,
                              seed=case["seed"])
        if rec.diverged_frame is not None:
            raise RuntimeError(f"{name}: OOPAO's loop diverged at frame {rec.diverged_frame}")
        np.save(im, sim.interaction_matrix)
        np.save(r, reconstructor)
        np.savez(path, y=rec.y, wfs=rec.wfs, positions_m=rec.positions_m, delay_frames=rec.delay_frames,
                 frame_rate_hz=rec.frame_rate_hz)
    truth = {"r0_m": case["r0"], "wfs_noise_nm": case["noise"] * surface_per_command(MECHANICAL_COUPLING),
             "layers": [[v, (90.0 - a) % 360.0, w] for v, a, w, _ in case["layers"]]}
    return path, truth, ["--interaction_matrix", str(im), "--reconstructor", str(r), "--command_unit", "peak"]


def twin_of(name: str, path: Path, options: list[str], out: Path) -> tuple[dict, list[str]]:
    """``eofnn twin`` on the record at ``path`` (``options``: its matrices and units), into ``out``: its
    identified.json and its stderr lines."""
    eofnn = str(Path(sys.executable).with_name("eofnn"))
    done = subprocess.run([eofnn, "twin", "--telemetry", str(path), *options, "--out", str(out), "--overwrite", "true"],
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{name}: eofnn twin failed: {done.stderr}")
    return json.loads((out / "identified.json").read_text()), done.stderr.splitlines()


def _angle(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def score(truth: dict, found: dict) -> dict:
    """Each target's error and verdict; found layers paired with the true ones by the pairing of least error."""
    q = found["quantities"]
    r0, noise = q["r0_m"]["value"], q["wfs_noise_nm"]["value"]
    out = {"r0_rel_error": r0 / truth["r0_m"] - 1, "noise_rel_error": noise / truth["wfs_noise_nm"] - 1,
           "layer_count": [len(found["layers"]), len(truth["layers"])]}
    pairs = []
    if found["layers"]:
        best = min(itertools.permutations(range(len(found["layers"])), min(len(found["layers"]), len(truth["layers"]))),
                   key=lambda p: sum(abs(found["layers"][j]["speed_mps"] / truth["layers"][i][0] - 1)
                                     + _angle(found["layers"][j]["direction_deg"], truth["layers"][i][1]) / 90.0
                                     for i, j in enumerate(p)))
        for i, j in enumerate(best):
            lay = found["layers"][j]
            pairs.append({"true": truth["layers"][i], "found": [lay["speed_mps"], lay["direction_deg"], lay["weight"]],
                          "speed_rel_error": lay["speed_mps"] / truth["layers"][i][0] - 1,
                          "direction_error_deg": _angle(lay["direction_deg"], truth["layers"][i][1])})
    out["layers"] = pairs
    out["pass"] = {
        "r0": abs(out["r0_rel_error"]) <= TARGETS["r0_rel"],
        "noise": abs(out["noise_rel_error"]) <= TARGETS["noise_rel"],
        "count": len(found["layers"]) == len(truth["layers"]),
        "speed": bool(pairs) and all(abs(p["speed_rel_error"]) <= TARGETS["speed_rel"] for p in pairs),
        "direction": bool(pairs) and all(p["direction_error_deg"] <= TARGETS["direction_deg"] for p in pairs)}
    return out


def _pct(x: float) -> str:
    return f"{100 * x:+.1f}%"


def _table(cases: dict) -> list[str]:
    """One row per case: the truth beside what the twin found, each target's verdict."""
    ok = {True: "✓", False: "✗"}
    rows = ["| case | r0 true → found (m) | noise true → found (nm, eofnn units) | layers true (m/s @ deg, Cn²) | "
            "found (speed, direction errors) | count |", "|---|---|---|---|---|---|"]
    for name, c in cases.items():
        t = c["truth"]
        true_layers = ", ".join(f"{v:g} @ {d:g} ({w:g})" for v, d, w in t["layers"])
        found = ", ".join(f"{p['found'][0]:.2f} @ {p['found'][1]:.1f} ({p['found'][2]:.2f}) "
                          f"({_pct(p['speed_rel_error'])} {ok[abs(p['speed_rel_error']) <= TARGETS['speed_rel']]}, "
                          f"{p['direction_error_deg']:.1f}° {ok[p['direction_error_deg'] <= TARGETS['direction_deg']]})"
                          for p in c["layers"])
        rows.append(f"| {name} | {t['r0_m']:g} → {c['r0_m'][0]:.3f} ± {c['r0_m'][1]:.3f} ({_pct(c['r0_rel_error'])}) "
                    f"{ok[c['pass']['r0']]} | {t['wfs_noise_nm']:.1f} → {c['wfs_noise_nm'][0]:.1f} "
                    f"({_pct(c['noise_rel_error'])}) {ok[c['pass']['noise']]} | {true_layers} | {found} | "
                    f"{c['layer_count'][0]} of {c['layer_count'][1]} {ok[c['pass']['count']]} |")
    return rows


def results_md(summary: dict) -> str:
    """The page: the final code's table, the first sight's (before any change), the notes."""
    lines = ["# eofnn twin on OOPAO records at conditions not used while developing it", "",
             "Script and conditions (seeds fixed before the first run): `experiments/interop/identify_unseen.py`. "
             f"Command: `{summary['command']}`. Targets: r0 and wind speed within 10%, direction within 10°, noise "
             "within 20%, the right layer count.", ""]
    if summary.get("cases"):
        lines += [f"## {summary.get('code', 'Final code')}", "", *_table(summary["cases"]), ""]
    for earlier in summary.get("earlier", []):  # the final code's tables before a later change
        lines += [f"## Earlier: {earlier['code']}", "", *_table(earlier["cases"]), ""]
    if summary.get("first_sight"):
        lines += [f"## First sight: {summary['first_sight']['code']}", "", *_table(summary["first_sight"]["cases"]), ""]
    return "\n".join([*lines, *summary.get("notes", []), ""])


def main(names: list[str]) -> None:
    RUNS.mkdir(parents=True, exist_ok=True)
    SUMMARY.mkdir(parents=True, exist_ok=True)
    summary_path = SUMMARY / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    summary.setdefault("cases", {})
    if summary["cases"] and summary.get("code") != CODE:  # the table of earlier code kept as it was
        summary.setdefault("earlier", []).insert(0, {"code": summary.get("code", "earlier code"),
                                                      "cases": summary["cases"]})
        summary["cases"] = {}
    summary["code"] = CODE
    summary.update({"conditions": {n: CASES[n] for n in CASES}, "targets": TARGETS, "frames": FRAMES,
                    "command": "OMP_NUM_THREADS=1 .venv/bin/python experiments/interop/identify_unseen.py"})
    for name in names:
        path, truth, options = record(name)
        found, stderr = twin_of(name, path, options, RUNS / f"twin_{name}")
        q = found["quantities"]
        row = {"truth": truth, "r0_m": [q["r0_m"]["value"], q["r0_m"]["uncertainty"]],
               "wfs_noise_nm": [q["wfs_noise_nm"]["value"], q["wfs_noise_nm"]["uncertainty"]],
               "dm_gain": q["dm_gain"]["value"], "outer_scale_m": q["outer_scale_m"]["value"],
               "found_layers": [{k: lay[k] for k in ("speed_mps", "speed_mps_se", "direction_deg", "direction_deg_se",
                                                      "weight")} for lay in found["layers"]],
               "warnings": [line for line in stderr if "warning" in line or "twin:" in line],
               **score(truth, found)}
        summary["cases"][name] = row
        print(json.dumps({"case": name, **{k: row[k] for k in ("r0_m", "wfs_noise_nm", "layer_count", "pass")},
                          "layers": row["layers"]}), flush=True)
        summary_path.write_text(json.dumps(summary, indent=1) + "\n")
        (SUMMARY / "results.md").write_text(results_md(summary))


if __name__ == "__main__":
    if sys.argv[1:] == ["page"]:  # results.md again from summary.json
        (SUMMARY / "results.md").write_text(results_md(json.loads((SUMMARY / "summary.json").read_text())))
    else:
        main(sys.argv[1:] or list(CASES))
