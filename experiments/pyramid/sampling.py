"""Does a pyramid loop close at a given pupil sampling? One small noise-free run per integrator gain.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python experiments/pyramid/sampling.py R0_M SAMPLES_PER_PIXEL N_ACROSS \
        DIAMETER_M [WIND_MPS [MODULATION]]

r0 at 658 nm (the scenario's default wavelength), one layer of ``WIND_MPS`` (default 2 m/s), delay 2, 300
frames, gains 0.3 and 0.5, the pyramid built past the scenario's sampling check (so that refused samplings can be
measured). Prints the median piston-removed residual over the pupil after 100 frames, the DM's fitting error of the
same phase and the open loop's residual.
"""

from __future__ import annotations

import sys

import torch

from eofnn.control.baselines import Integrator
from eofnn.sim.atmosphere.turbulence import Atmosphere
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.loop.plant import Plant
from eofnn.sim.loop.pyramid import PyramidTurbulence
from eofnn.sim.loop.runner import run_loop
from eofnn.sim.sensing.sensor import build_sensor

FRAMES, SETTLE = 300, 100


def main(argv: list[str]) -> None:
    r0, spp, n_across, diameter = float(argv[0]), int(argv[1]), int(argv[2]), float(argv[3])
    wind = float(argv[4]) if len(argv) > 4 else 2.0
    modulation = float(argv[5]) if len(argv) > 5 else 3.0
    atmosphere = Atmosphere(r0_m=r0, layers=[{"wind_speed_mps": wind}], screen_frames=400, model="exact")
    grid = ActuatorGrid(diameter, n_across, 0.0)
    sensor = build_sensor({"kind": "pyramid", "modulation_lambda_over_d": modulation, "samples_per_pixel": spp})
    for gain in (0.3, 0.5):
        turbulence = PyramidTurbulence(atmosphere, grid, 1000.0, 1, "test", 1, [], sensor)
        result = run_loop(turbulence, Plant(delay_frames=2), Integrator(gain), FRAMES, record=())
        out = turbulence.products(0, FRAMES)
        ops = turbulence.operators
        fit = ops.pupil_rms(out["z"], out["sum"], out["sumsq"], -out["fit"])
        open_loop = ops.pupil_rms(out["z"], out["sum"], out["sumsq"], torch.zeros_like(out["fit"]))
        residual = result.pupil_residual_rms_nm[:, SETTLE:]
        print(f"r0={r0} m samples_per_pixel={spp} n_across={n_across} D={diameter} m modulation={modulation} "
              f"gain={gain}: residual {float(residual.median()):.1f} nm, fitting {float(fit[:, SETTLE:].median()):.1f}"
              f" nm, open loop {float(open_loop.median()):.1f} nm, diverged {result.diverged}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
