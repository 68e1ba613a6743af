"""Your system's twin through OOPAO: record OOPAO's closed loop, then run eofnn's whole twin path on the record alone.

1. **Record** (the "telescope"): OOPAO's geometric Shack-Hartmann loop, one frozen-flow layer of OOPAO's atmosphere,
   closed by a dithered integrator (gain 0.4, 10 nm of white dither), white slope noise of a stated RMS per
   actuator added to the slopes (``--noise-nm``), or OOPAO's diffractive Shack-Hartmann with photon noise of an
   I-band guide star (``--magnitude``). Written as a real-time computer would write it: ``loop.npz`` holds ``y``,
   ``wfs`` (``R @ slopes``, nm at the peak of one influence function: OOPAO's unit), the actuator positions, the
   delay and the frame rate; OOPAO's interaction matrix (``im.npy``, ``(S, K)``, slopes per nm) and reconstructor
   (``r.npy``, ``(K, S)``) beside it. Nothing else.
2. **eofnn twin** --telemetry loop.npz --interaction_matrix im.npy --reconstructor r.npy --command_unit peak.
3. **eofnn fit** --scenario twin/twin.yaml --predictor.data.target dm_fit: a predictor trained in the twin
   (``--target measured``: on what the twin's sensor reports in place of the DM's fit of its true phase).
4. **eofnn replay** of it on the recorded telemetry: the guard (``replay.json``'s ``guard``) deploys it only if it
   beats the recording integrator on the record by more than 2 standard errors.
5. **eofnn export** --guard replay.json: the filter for the real-time computer, written only if deployed.

Nothing of OOPAO's settings (r0, L0, wind, noise, magnitude) is passed to eofnn: only the three files. The summary
prints OOPAO's truth beside what was identified; the truth is the simulator's knowledge, shown only for the report.
OOPAO's wind direction ``a`` moves the turbulence along ``90 - a`` degrees of its DM's positions; the truth is shown
in eofnn's convention. Residuals of the replay are nm of OOPAO's commands (the record's unit; the filter is linear).

    python examples/twin_path.py                                   # 10 x 10 on 2 m, 3000 frames (a few minutes)
    python examples/twin_path.py --n-subap 20 --diameter 4 --frames 4000 --wind 15 --direction 30 --seed 7

``--wrong-direction DEG`` turns the identified winds by DEG before the fit (``twin/twin_wrong.yaml``, a twin
deliberately wrong; ``wrong_eof.ckpt``, ``guard_wrong/``): the guard should then keep the integrator. The last line
printed is the summary as JSON (``--out`` keeps every file; default a temporary folder).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

#: The fit in the twin: small, so that the default path stays a few minutes on one core.
FIT = {"--predictor.data.frames": 3000, "--predictor.data.val_frames": 600, "--predictor.data.sequence_frames": 3600}
RECORD_GAIN, DITHER_NM = 0.4, 10.0


def parse(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-subap", type=int, default=10, help="Shack-Hartmann subapertures across (default 10)")
    parser.add_argument("--diameter", type=float, default=2.0, help="telescope diameter, m (default 2)")
    parser.add_argument("--frames", type=int, default=3000, help="frames recorded at 1 kHz (default 3000)")
    parser.add_argument("--seed", type=int, default=21, help="OOPAO's realisation and noise (default 21)")
    parser.add_argument("--r0", type=float, default=0.12, help="OOPAO's r0 at 500 nm, m (default 0.12)")
    parser.add_argument("--wind", type=float, default=12.0, help="OOPAO's wind speed, m/s (default 12)")
    parser.add_argument("--direction", type=float, default=30.0, help="OOPAO's wind direction, deg (default 30)")
    parser.add_argument("--noise-nm", type=float, default=25.0,
                        help="white slope noise per actuator, nm of OOPAO's commands (geometric sensor; default 25)")
    parser.add_argument("--magnitude", type=float, default=None,
                        help="OOPAO's diffractive Shack-Hartmann with photon noise of an I-band star of this "
                             "magnitude in place of the geometric sensor and --noise-nm")
    parser.add_argument("--rcond", type=float, default=0.15,
                        help="OOPAO's reconstructor keeps singular values above this fraction (default 0.15)")
    parser.add_argument("--wrong-direction", type=float, default=0.0,
                        help="rotate twin.yaml's winds by this many degrees before the fit (default 0: the twin)")
    parser.add_argument("--target", choices=("dm_fit", "measured"), default="dm_fit",
                        help="the fit's target in the twin: the DM's fit of the twin's true phase (default) or what "
                             "the twin's sensor reports")
    parser.add_argument("--fit-frames", type=int, default=FIT["--predictor.data.frames"],
                        help="training frames of the fit in the twin (default 3000)")
    parser.add_argument("--out", default=None, help="folder for every file (default: a temporary folder)")
    args = parser.parse_args(argv)
    for name, low in (("n_subap", 4), ("frames", 1000), ("fit_frames", 500)):
        if getattr(args, name) < low:
            parser.error(f"--{name.replace('_', '-')}={getattr(args, name)} is invalid: at least {low}")
    if args.noise_nm < 0:
        parser.error(f"--noise-nm={args.noise_nm} is invalid: 0 or more")
    return args


def record(args, folder: Path) -> dict:
    """OOPAO's dithered integrator loop written as telemetry files; OOPAO's truth (for the report only)."""
    from eofnn.interop.loop import IntegratorControl, require_recorded, run_closed_loop, with_slope_noise
    from eofnn.interop.oopao import OopaoLoop

    photon = args.magnitude is not None
    sim = OopaoLoop(n_subapertures=args.n_subap, diameter_m=args.diameter,
                    sensor="shack_hartmann" if photon else "geometric", photon_noise=photon,
                    magnitude=args.magnitude if photon else 8.0, r0_m=args.r0, wind_speed_mps=args.wind,
                    wind_direction_deg=args.direction, rcond=args.rcond)
    reconstructor = sim.reconstructor
    if not photon and args.noise_nm > 0:  # white slope noise of args.noise_nm per actuator after R
        with_slope_noise(sim, args.noise_nm, args.seed + 1000)
    rec = require_recorded(run_closed_loop(sim, IntegratorControl(RECORD_GAIN, dither_nm=DITHER_NM, seed=args.seed),
                                           args.frames, seed=args.seed), RECORD_GAIN, sim)
    np.savez(folder / "loop.npz", y=rec.y, wfs=rec.wfs, positions_m=rec.positions_m, delay_frames=rec.delay_frames,
             frame_rate_hz=rec.frame_rate_hz)
    np.save(folder / "im.npy", sim.interaction_matrix)
    np.save(folder / "r.npy", reconstructor)
    settle = min(500, args.frames // 4)
    return {"r0_m": args.r0, "outer_scale_m": sim.settings["outer_scale_m"], "wind_speed_mps": args.wind,
            "wind_direction_deg_eofnn": (90.0 - args.direction) % 360.0,
            "wfs_noise_nm_eofnn": None if photon else args.noise_nm * sim.surface_per_command,
            "residual_opd_rms_nm": float(np.median(rec.residual_rms_nm[settle:])), "n_actuators": sim.n_actuators,
            "n_seen_modes": sim.n_seen}


def cli(*argv) -> None:
    """One eofnn command, as on the command line; a non-zero exit stops the example in one line."""
    from eofnn.cli.main import main

    code = main([str(a) for a in argv])
    if code:
        raise SystemExit(f"eofnn {argv[0]} exited with {code}")


def rotated(twin_yaml: Path, degrees: float) -> Path:
    """A copy of twin.yaml whose layers' wind directions are turned by ``degrees`` (a deliberately wrong twin)."""
    config = yaml.safe_load(twin_yaml.read_text())
    for layer in config["atmosphere"]["layers"]:
        layer["wind_direction_deg"] = float((layer["wind_direction_deg"] + degrees) % 360.0)
    out = twin_yaml.with_name("twin_wrong.yaml")
    out.write_text(yaml.safe_dump(config, sort_keys=False))
    return out


def identify(args, folder: Path) -> dict:
    """Record in OOPAO, then ``eofnn twin`` on the files; OOPAO's truth (for the report only)."""
    folder.mkdir(parents=True, exist_ok=True)
    truth = record(args, folder)
    cli("twin", "--telemetry", folder / "loop.npz", "--interaction_matrix", folder / "im.npy",
        "--reconstructor", folder / "r.npy", "--command_unit", "peak", "--screen_frames", args.fit_frames + 1500,
        "--seed", args.seed, "--out", folder / "twin", "--overwrite", "true")
    return truth


def train_and_guard(args, folder: Path) -> dict:
    """``eofnn fit`` in the twin (its winds turned by ``args.wrong_direction``), ``eofnn replay`` of it on the record
    (the guard) and ``eofnn export`` if the guard deployed it; the replay's figures and the guard's decision."""
    name = "wrong" if args.wrong_direction else "twin"
    scenario = folder / "twin" / "twin.yaml"
    scenario = rotated(scenario, args.wrong_direction) if args.wrong_direction else scenario
    ckpt, guard_dir = folder / f"{name}_eof.ckpt", folder / ("guard_wrong" if args.wrong_direction else "guard")
    fit = {**FIT, "--predictor.data.frames": args.fit_frames, "--predictor.data.val_frames": args.fit_frames // 5,
           "--predictor.data.sequence_frames": args.fit_frames + args.fit_frames // 5}
    cli("fit", "--scenario", scenario, "--predictor.data.target", args.target,
        *[v for kv in fit.items() for v in kv], "--predictor.data.seed", args.seed, "--out", ckpt, "--overwrite", "true")
    start = min(1000, args.frames // 3)
    cli("replay", "--checkpoint", ckpt, "--telemetry", folder / "loop.npz", "--start", start, "--out", guard_dir,
        "--overwrite", "true")
    replayed = json.loads((guard_dir / "replay.json").read_text())
    guard, exported = replayed["guard"], None
    if guard["deployed"] == "predictor":
        exported = folder / ("filter_wrong.fits" if args.wrong_direction else "filter.fits")
        cli("export", "--checkpoint", ckpt, "--guard", guard_dir / "replay.json", "--out", exported,
            "--overwrite", "true")
    return {"target": args.target, "wrong_direction_deg": args.wrong_direction, "checkpoint": str(ckpt),
            "replay": str(guard_dir / "replay.json"),
            "replay_rms_nm_oopao_units": {"predictor": replayed["predictor"]["median_rms_nm"],
                                          "recording_integrator": replayed["own_controller"]["median_rms_nm"]},
            "replay_frames": [start, args.frames],
            "guard": {k: guard[k] for k in ("deployed", "gain_nm2", "scatter_nm2", "sigmas", "why")},
            "exported": None if exported is None else str(exported)}


def identified(folder: Path) -> dict:
    """What ``eofnn twin`` found, from identified.json."""
    found = json.loads((folder / "twin" / "identified.json").read_text())
    q = found["quantities"]
    return {"r0_m": [q["r0_m"]["value"], q["r0_m"]["uncertainty"]], "outer_scale_m": q["outer_scale_m"]["value"],
            "wfs_noise_nm": [q["wfs_noise_nm"]["value"], q["wfs_noise_nm"]["uncertainty"]],
            "dm_gain": q["dm_gain"]["value"],
            "layers": [{k: round(lay[k], 3) for k in ("speed_mps", "direction_deg", "weight")}
                       for lay in found["layers"]]}


def run(args, folder: Path) -> dict:
    """The whole path; the summary (``report`` prints it)."""
    truth = identify(args, folder)
    return {"truth_simulator_knowledge": truth, "identified": identified(folder), **train_and_guard(args, folder),
            "folder": str(folder)}


def report(summary: dict) -> str:
    """The summary in a few lines: identified against the simulator's truth, the replay, the guard."""
    t, i = summary["truth_simulator_knowledge"], summary["identified"]
    lay = i["layers"][0] if i["layers"] else {"speed_mps": float("nan"), "direction_deg": float("nan")}
    noise = t["wfs_noise_nm_eofnn"]
    rms = summary["replay_rms_nm_oopao_units"]
    lines = [
        "identified from the telemetry alone (OOPAO's truth, simulator knowledge, in brackets):",
        f"  r0 {i['r0_m'][0]:.4f} +- {i['r0_m'][1] or 0:.4f} m [{t['r0_m']}] ({100 * (i['r0_m'][0] / t['r0_m'] - 1):+.1f}%)",
        f"  wind {lay['speed_mps']:.2f} m/s [{t['wind_speed_mps']}] at {lay['direction_deg']:.1f} deg "
        f"[{t['wind_direction_deg_eofnn']:.1f}]; {len(i['layers'])} layer(s) [1]",
        f"  WFS noise {i['wfs_noise_nm'][0]:.1f} nm per actuator, eofnn units ["
        + ("not known: photon noise" if noise is None else f"{noise:.1f}") + "]",
        f"  DM gain x optical gain {i['dm_gain']:.3f}; L0 {i['outer_scale_m']:.0f} m [{t['outer_scale_m']}]",
        f"replay on the record (frames {summary['replay_frames'][0]}-{summary['replay_frames'][1]}), median RMS, nm of"
        f" OOPAO's commands: twin-trained {rms['predictor']:.2f}, recording integrator {rms['recording_integrator']:.2f}"
        f" (variance ratio {(rms['recording_integrator'] / rms['predictor']) ** 2:.2f})",
        f"guard: {summary['guard']['deployed']}: {summary['guard']['why']}",
        f"exported: {summary['exported']}"]
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse(argv)
    with tempfile.TemporaryDirectory() as tmp:
        summary = run(args, Path(args.out) if args.out else Path(tmp))
        print(report(summary))
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
