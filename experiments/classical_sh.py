"""The classical side of a small Shack-Hartmann loop at its strongest: reconstructors and PFC's noise model.

    PYTHONPATH=$PWD OMP_NUM_THREADS=1 .venv/bin/python experiments/classical_sh.py --magnitudes none,8,10,12,13 \
        --out experiments/runs/classical_sh/integrator.json
    PYTHONPATH=$PWD OMP_NUM_THREADS=1 .venv/bin/python experiments/classical_sh.py --pfc --magnitudes 10,12,13 \
        --out experiments/runs/classical_sh/pfc.json

A 4 m telescope, 16 x 16 actuators (15 x 15 Fried subapertures of 0.27 m), r0 = 0.15 m at 500 nm, L0 = 20 m, one
10 m/s layer, 1 kHz, two frames of delay; photon noise of an R-band guide star of each ``--magnitudes`` (``none``: no
detector). Without ``--pfc``: the best-gain integrator (gains 0.1 to 0.8, ``--frames`` frames, median residual over
the pupil after ``--settle`` frames, 2 realisations of the scan stream) through the least-squares reconstructor and
through the MMSE one (``sensor.reconstructor: mmse``) with its noise term one frame's (weight 1) and the
integrator's average's (weight ``g / (2 - g)``). With ``--pfc``: predictive Fourier control (no aliases, alpha
0.99, 2000 frames of dithered telemetry) with white noise per actuator and with the reconstructor's coloured noise
(``pfc.noise_covariance``), through each reconstructor.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

GAINS = (0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)


def scenario(magnitude: float | None, reconstructor: str, screen_frames: int):
    from eofnn.sim.scenario import Scenario

    sensor = {"kind": "shack_hartmann", "reconstructor": reconstructor}
    if magnitude is not None:
        sensor["detector"] = {"magnitude": magnitude}
    return Scenario.from_dict({"grid": {"diameter_m": 4.0, "n_across": 16, "obstruction": 0.0},
                               "atmosphere": {"r0_m": 0.15, "r0_wavelength_m": 5e-7, "outer_scale_m": 20.0,
                                              "layers": [{"wind_speed_mps": 10.0}], "screen_frames": screen_frames},
                               "plant": {"delay_frames": 2}, "sensor": sensor})


def integrator(magnitude: float | None, frames: int, settle: int) -> dict:
    from eofnn.control.baselines import Integrator
    from eofnn.sim.loop.runner import run_loop

    out = {}
    for name, reconstructor, weight in (("least_squares", "least_squares", None), ("mmse", "mmse", None),
                                        ("mmse_loop_weighted", "mmse", "loop")):
        sc = scenario(magnitude, reconstructor, frames + 10)
        scan = {}
        for gain in GAINS:
            turbulence = sc.turbulence(1, "scan", 2)
            turbulence.mmse_noise_weight = gain / (2 - gain) if weight == "loop" else 1.0
            result = run_loop(turbulence, sc.plant, Integrator(gain), frames, noise_seed=11, record=())
            scan[gain] = None if result.diverged else float(result.pupil_residual_rms_nm[:, settle:].median())
        best = min((v, g) for g, v in scan.items() if v is not None)
        out[name] = {"best_nm": best[0], "gain": best[1], "scan": scan}
        print(magnitude, name, f"{best[0]:.1f} nm at gain {best[1]}", flush=True)
    return out


def pfc(magnitude: float | None, frames: int, settle: int) -> dict:
    from eofnn.control.registry import FROM_TELEMETRY, build_controller
    from eofnn.evaluation.config import PredictorConfig

    out = {}
    for reconstructor in ("least_squares", "mmse"):
        sc = scenario(magnitude, reconstructor, 3000)
        for noise in ("white", "reconstructor"):
            cfg = PredictorConfig(controller="pfc", pfc={"aliases": 0, "alpha": 0.99, "noise_covariance": noise},
                                  data={"frames": 2000, "seed": 5, "dither_nm": 5.0})
            rms = sc.median_residual_nm(build_controller(cfg, FROM_TELEMETRY["pfc"](cfg, sc)), frames, 1, "scan",
                                        settle)
            out[f"{reconstructor}/{noise}"] = rms
            print(magnitude, reconstructor, noise, f"{rms:.1f} nm", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--magnitudes", default="none,8,10,12,13")
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--settle", type=int, default=300)
    parser.add_argument("--pfc", action="store_true")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    run = pfc if args.pfc else integrator
    results = {m: run(None if m == "none" else float(m), args.frames, args.settle)
               for m in args.magnitudes.split(",")}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
