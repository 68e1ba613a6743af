"""How well ``eofnn twin`` identifies a system from its telemetry alone: record at stated conditions, identify, compare.

Two sources of telemetry, each case recorded by a dithered integrator (10 nm of dither; eofnn's default gain, 0.4
in OOPAO) and written with
``y``, ``wfs``, positions, the delay and the frame rate only (the truth is kept aside, never given to the twin):

- ``eofnn``: eofnn's geometric Shack-Hartmann, 4 m, 16 actuators across (Fried), photon noise of an R = 8-10 guide
  star, 4000 frames, one or two layers of exact frozen flow; the sensor's interaction matrix and reconstructor (which
  eofnn's loop writes beside its slopes) are given, so that the twin knows the sensor is a Shack-Hartmann;
- ``oopao``: OOPAO's geometric Shack-Hartmann, 4 m, 20 x 20 subapertures, one layer of OOPAO's atmosphere, white
  slope noise of known RMS (25 nm per actuator in OOPAO's command units, 74.8 nm in eofnn's) added to its slopes,
  4000 frames; OOPAO's interaction matrix and reconstructor are given, commands are nm of influence-function peak
  (``--command_unit peak``). OOPAO's wind direction ``a`` moves the turbulence along ``90 - a`` degrees of its DM's
  positions (``vy = v cos a``, ``vx = v sin a``).

Run (each case a few minutes on one core)::

    python examples/twin_accuracy.py eofnn A B C D --folder runs/twin_accuracy
    python examples/twin_accuracy.py oopao O1 O2 --folder runs/twin_accuracy

One JSON line per case: the truth beside what the twin found (``docs/twin.md`` has the table).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

EOFNN_CASES = {  # r0 at 500 nm; layers (speed m/s, direction deg, Cn2 fraction); R magnitude; seed
    "A": {"r0": 0.15, "layers": [(15.0, 120.0, 1.0)], "magnitude": 9.0, "seed": 7},
    "B": {"r0": 0.10, "layers": [(6.0, -45.0, 0.6), (14.0, 200.0, 0.4)], "magnitude": 8.0, "seed": 11},
    "C": {"r0": 0.08, "layers": [(8.0, 60.0, 0.5), (13.0, 60.0, 0.5)], "magnitude": 8.0, "seed": 5},
    "D": {"r0": 0.20, "layers": [(7.0, 250.0, 1.0)], "magnitude": 10.0, "seed": 3},
    "E": {"r0": 0.12, "layers": [(9.0, 170.0, 0.7), (20.0, 100.0, 0.3)], "magnitude": 9.0, "seed": 31},
    "F": {"r0": 0.09, "layers": [(22.0, -20.0, 1.0)], "magnitude": 8.0, "seed": 32},
}
OOPAO_CASES = {  # r0 at 500 nm, L0, one layer (speed, OOPAO direction), seed
    "O1": {"r0": 0.12, "outer_scale": 25.0, "speed": 12.0, "direction": 0.0, "seed": 21},
    "O2": {"r0": 0.16, "outer_scale": 25.0, "speed": 18.0, "direction": 30.0, "seed": 22},
    "O3": {"r0": 0.10, "outer_scale": 25.0, "speed": 8.0, "direction": 45.0, "seed": 23},
}
FRAMES = 4000
OOPAO_NOISE_NM = 25.0


def record_eofnn(name: str, folder: Path) -> tuple[Path, dict, list[str]]:
    """eofnn simulate at the case's conditions; the telemetry without its truth, and the truth."""
    import torch
    import yaml

    from eofnn.telemetry.record import TELEMETRY_REQUIRED, Telemetry

    case = EOFNN_CASES[name]
    scenario = {"grid": {"diameter_m": 4.0, "n_across": 16, "obstruction": 0.0},
                "atmosphere": {"r0_m": case["r0"], "r0_wavelength_m": 5e-7, "outer_scale_m": 20.0, "model": "exact",
                               "screen_frames": FRAMES + 200, "remove_ptt": True,
                               "layers": [{"cn2_fraction": w, "wind_speed_mps": v, "wind_direction_deg": d}
                                          for v, d, w in case["layers"]]},
                "frame_rate_hz": 1000.0, "plant": {"delay_frames": 2},
                "sensor": {"kind": "shack_hartmann", "detector": {"band": "R", "magnitude": case["magnitude"]}}}
    (folder / f"{name}.yaml").write_text(yaml.safe_dump(scenario))
    full = folder / f"{name}_full.fits"
    if not full.exists():
        subprocess.run(["eofnn", "simulate", "--scenario", str(folder / f"{name}.yaml"), "--predictor.controller",
                        "dithered_integrator", "--predictor.data.dither_nm", "10",
                        "--frames", str(FRAMES), "--seed", str(case["seed"]), "--out", str(full)], check=True)
    tel = Telemetry.load(full, required=TELEMETRY_REQUIRED)
    s, y, wfs = (a.numpy().reshape(-1, a.shape[-1]) for a in (tel.s, tel.y, tel.wfs))
    truth = {"r0_m": case["r0"], "wfs_noise_nm": float(np.sqrt(((wfs - s - y) ** 2).mean())),  # DM gain 1
             "layers": case["layers"]}
    path = folder / f"{name}.npz"
    if not path.exists():
        Telemetry(y=torch.as_tensor(y), wfs=torch.as_tensor(wfs), delay_frames=2, frame_rate_hz=1000.0,
                  positions_m=tel.positions_m).save(path)
    # The Shack-Hartmann's matrices, as its loop writes them: without them the twin cannot tell the sensor and takes
    # the subaperture average, whose view of the same turbulence is ~4x smaller in variance (r0 ~0.4x).
    np.save(folder / f"{name}_im.npy", tel.interaction_matrix.numpy())
    np.save(folder / f"{name}_r.npy", tel.reconstructor.numpy())
    return path, truth, ["--interaction_matrix", str(folder / f"{name}_im.npy"),
                         "--reconstructor", str(folder / f"{name}_r.npy")]


def record_oopao(name: str, folder: Path) -> tuple[Path, dict, list[str]]:
    """OOPAO's loop at the case's conditions with white slope noise of known RMS; telemetry, truth, twin options."""
    from eofnn.interop.loop import IntegratorControl, run_closed_loop, with_slope_noise
    from eofnn.interop.oopao import OopaoLoop

    case = OOPAO_CASES[name]
    sim = OopaoLoop(n_subapertures=20, diameter_m=4.0, sensor="geometric", r0_m=case["r0"],
                    outer_scale_m=case["outer_scale"], wind_speed_mps=case["speed"],
                    wind_direction_deg=case["direction"], rcond=0.15)
    reconstructor = sim.reconstructor
    path = folder / f"{name}.npz"
    if not path.exists():
        with_slope_noise(sim, OOPAO_NOISE_NM, case["seed"] + 1000)
        rec = run_closed_loop(sim, IntegratorControl(0.4, dither_nm=10.0, seed=case["seed"]), FRAMES, seed=case["seed"])
        np.savez(path, y=rec.y, wfs=rec.wfs, positions_m=rec.positions_m, delay_frames=rec.delay_frames,
                 frame_rate_hz=rec.frame_rate_hz)
        np.save(folder / f"{name}_im.npy", sim.interaction_matrix)
        np.save(folder / f"{name}_r.npy", reconstructor)
    truth = {"r0_m": case["r0"], "wfs_noise_nm": OOPAO_NOISE_NM * sim.surface_per_command,
             "layers": [(case["speed"], 90.0 - case["direction"], 1.0)]}
    options = ["--interaction_matrix", str(folder / f"{name}_im.npy"), "--reconstructor", str(folder / f"{name}_r.npy"),
               "--command_unit", "peak"]
    return path, truth, options


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", choices=("eofnn", "oopao"))
    parser.add_argument("cases", nargs="+")
    parser.add_argument("--folder", default="runs/twin_accuracy")
    args = parser.parse_args()
    folder = Path(args.folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name in args.cases:
        path, truth, options = (record_eofnn if args.source == "eofnn" else record_oopao)(name, folder)
        out = folder / f"twin_{name}"
        subprocess.run(["eofnn", "twin", "--telemetry", str(path), *options, "--out", str(out), "--overwrite", "true"],
                       check=True)
        found = json.loads((out / "identified.json").read_text())
        q = found["quantities"]
        print(json.dumps({"case": name, "truth": truth,
                          "r0_m": [q["r0_m"]["value"], q["r0_m"]["uncertainty"]],
                          "outer_scale_m": q["outer_scale_m"]["value"],
                          "wfs_noise_nm": [q["wfs_noise_nm"]["value"], q["wfs_noise_nm"]["uncertainty"]],
                          "dm_gain": q["dm_gain"]["value"],
                          "layers": [[round(lay[k], 3) for k in ("speed_mps", "speed_mps_se", "direction_deg",
                                                                 "direction_deg_se", "weight")]
                                     for lay in found["layers"]]}), flush=True)


if __name__ == "__main__":
    sys.exit(main())
