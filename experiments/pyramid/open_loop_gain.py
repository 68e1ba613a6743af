"""Why the open-loop EOF diverged through eofnn's pyramid: the slope of what its training inputs were against the
truth ``s = P F phi``, beside the slope of the POL values the loop gives it.

On ``configs/realistic_pyr.yaml``'s scenario (``--compensated``: with ``sensor.optical_gain_compensation``), one
realisation of ``--frames`` frames: (1) the pyramid's reading of the uncorrected turbulence (what open-loop training
data were before ``eofnn.data.stream.open_loop_recorded``), (2) the POL values ``wfs + y`` of a closed loop (a leak-free
integrator of gain 0.5 plus 10 nm of dither, the first 50 frames dropped), each regressed on ``s`` (one slope over
all actuators and frames). Prints one JSON line.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python experiments/pyramid/open_loop_gain.py [--compensated] [--frames 300]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import yaml

from eofnn.control.baselines import Dithered, Integrator
from eofnn.data.history import pseudo_open_loop
from eofnn.seeding import torch_generator
from eofnn.sim.loop.runner import record_loop
from eofnn.sim.scenario import Scenario

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "realistic_pyr.yaml"


def slope(x, s) -> float:
    return float((x * s).sum() / (s * s).sum())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--compensated", action="store_true")
    parser.add_argument("--frames", type=int, default=300)
    args = parser.parse_args(argv)
    scenario_dict = yaml.safe_load(CONFIG.read_text())["scenario"]
    scenario_dict["sensor"]["optical_gain_compensation"] = args.compensated
    scenario_dict["atmosphere"]["screen_frames"] = max(512, args.frames)
    scenario = Scenario.from_dict(scenario_dict)
    s, read = scenario.turbulence(5, "diag", 1).open_loop(0, args.frames, scenario.plant,
                                                                     torch_generator(5, "diag", 1))
    result = record_loop(scenario.turbulence(5, "diag2", 1), scenario.plant,
                         Dithered(Integrator(0.5, 0.0), 10.0, 0), args.frames, noise_seed=3, record=("s", "y", "wfs"))
    tel = result.telemetry
    pol = pseudo_open_loop(tel.wfs, tel.y)
    print(json.dumps({"compensated": args.compensated, "frames": args.frames,
                      "open_loop_reading_slope": slope(read, s), "closed_loop_pol_slope": slope(pol[:, 50:], tel.s[:, 50:]),
                      "open_loop_rms_nm": float(s.pow(2).mean().sqrt())}))


if __name__ == "__main__":
    main()
