"""Why the LQG loses to the integrator in OOPAO's SH loop: a small diagnostic (20 x 20 on 4 m, I = 8, 20 m/s).

Records the antialias study's telemetry (3 dithered-integrator recordings of 2000 frames, seeds as the study's), forms
the POL values with the identified DM gain, and closes the loop on the scan realisation (seed 3) with: the integrator
at its best gain, the LQG of each AR order as built today, the same with the measurement noise scaled, and the
random-walk (POL integrator) model. Per KL mode group it prints the variance of the measured residual (``wfs``
projected on the KL modes; the noise adds the same to every controller).

    OMP_NUM_THREADS=1 PYTHONPATH=. python experiments/interop/lqg_small/diagnose.py OUT.json [RHOS [no-integrator] | dm-gain]
"""

from __future__ import annotations

import json
import sys
import time

import torch

from eofnn.control.classical import ModalLQG
from eofnn.control.kalman import fit_ar, kalman_gain
from eofnn.control.modal import modal_statistics
from eofnn.data.history import pseudo_open_loop
from eofnn.interop.loop import IntegratorControl, TorchControl, require_recorded, run_closed_loop
from eofnn.interop.oopao import OopaoLoop
from eofnn.studies.loop_scans import _grid_indices
from eofnn.training.identify import identify_plant

SEED, FRAMES, LOOP, SETTLE = 0, 2000, 1000, 200
sim = OopaoLoop(20, 4.0, photon_noise=True, magnitude=8.0, dm_gain=2.0, wind_speed_mps=20.0)
t0 = time.time()
telemetry = []
for i in range(3):
    rec = require_recorded(run_closed_loop(sim, IntegratorControl(0.25, 10.0, seed=SEED + 140 + i), FRAMES,
                                           SEED + 40 + i), 0.25, sim)
    telemetry.append(rec.telemetry(start=SETTLE))
plant = identify_plant(telemetry)
pol = torch.stack([pseudo_open_loop(s.wfs, s.y, plant.dm_gain) for s in telemetry])
stats = modal_statistics(pol, grid_indices=_grid_indices(sim))
print(f"recorded in {time.time() - t0:.0f} s; dm gain {plant.dm_gain:.4f}, K={pol.shape[-1]}", flush=True)
modes = stats.modes
groups = [(0, 10), (10, 50), (50, 150), (150, modes.shape[1])]
out = {"dm_gain": plant.dm_gain, "noise_rms_nm_quantiles": [float(v) for v in stats.noise_variance.sqrt().quantile(
    torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64))], "runs": {}}


def lqg(order: int | str, rho: float = 1.0) -> ModalLQG:
    if order == "rw":  # random walk: a1 = 1, q the variance of the noise-free first difference
        ar = torch.zeros(modes.shape[1], 2, dtype=torch.float64)
        ar[:, 0] = 1.0
        q = (2 * (stats.autocovariance[:, 0] - stats.autocovariance[:, 1])).clamp(min=1e-9)
    else:
        ar, q = fit_ar(order, stats.autocovariance, stats.noise_variance)
    r = rho * stats.noise_variance
    gain, _ = kalman_gain(ar, q, r)
    return ModalLQG(modes, ar, q, r, gain, sim.delay_frames, plant.dm_gain)


def run(name: str, control) -> None:
    t = time.time()
    rec = run_closed_loop(sim, control, LOOP, SEED + 3)
    rms = rec.metrics(SETTLE).median_rms_nm
    per_mode = (torch.from_numpy(rec.wfs[SETTLE:]) @ modes).pow(2).mean(0) if rec.diverged_frame is None else None
    out["runs"][name] = {"median_rms_nm": rms,
                         "measured_var_by_group_nm2": None if per_mode is None else
                         {f"{a}-{b}": float(per_mode[a:b].mean()) for a, b in groups}}
    print(f"{name:>24}: {rms}  {out['runs'][name]['measured_var_by_group_nm2']}  ({time.time() - t:.0f} s)",
          flush=True)


if len(sys.argv) > 2 and sys.argv[2] == "dm-gain":  # the LQG's sensitivity to its DM-gain model, x 0.95 and x 1.05
    for order, rho in ((2, 1.0), (1, 0.125)):
        for factor in (0.95, 1.05):
            model = lqg(order, rho)
            model.dm_gain_model = plant.dm_gain * factor
            run(f"lqg {order} rho={rho} dm x {factor}", TorchControl(model, sim.delay_frames))
    json.dump(out, open(sys.argv[1], "w"), indent=1)
    sys.exit(0)
RHOS = [float(v) for v in sys.argv[2].split(",")] if len(sys.argv) > 2 else [1.0, 4.0, 16.0]
if len(sys.argv) <= 3:
    for g in (0.25, 0.3, 0.35):
        run(f"integrator g={g}", IntegratorControl(g))
for order in (1, 2, "rw"):
    for rho in RHOS:
        run(f"lqg {order} rho={rho}", TorchControl(lqg(order, rho), sim.delay_frames))
json.dump(out, open(sys.argv[1], "w"), indent=1)
