"""The LQG before and after its noise-scale scan in OOPAO's SH loop at small scale (20 x 20 on 4 m, photon noise,
I = 8, 20 m/s, 2 frames, DM applying 2x): the best-gain integrator, the modal integrator, the LQG as tuned before
(AR order 1 or 2, the identified noise as is) and the LQG as tuned now (random walk, AR(1), AR(2) x the noise scales,
on past the edge: eofnn.studies.loop_scans.scan_lqg), each built from the same telemetry as the antialias study's
(3 dithered-integrator recordings of 2000 frames, seeds 40-42 / dither 140-142), tuned on realisation 3 and scored on
realisations 2, 20, 21 (the study's seeds with --seed 0), 1000 frames each, the first 200 not scored.

    OMP_NUM_THREADS=1 PYTHONPATH=. python experiments/interop/lqg_small/run.py experiments/interop/lqg_small/summary.json
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import torch

from eofnn.data.history import pseudo_open_loop
from eofnn.interop.loop import IntegratorControl, TorchControl, require_recorded, run_closed_loop, scan_integrator
from eofnn.interop.oopao import OopaoLoop
from eofnn.studies.antialias import AntiAliasConfig
from eofnn.studies.loop_scans import scan_lqg, scan_modal
from eofnn.training.identify import identify_plant

c = AntiAliasConfig(oracle=False)
sim = OopaoLoop(20, 4.0, photon_noise=True, magnitude=8.0, dm_gain=2.0, wind_speed_mps=20.0)
started = time.time()
telemetry = []
for i in range(c.train_sequences):
    record = run_closed_loop(sim, IntegratorControl(c.record_gain, c.dither_nm, seed=c.seed + 140 + i),
                             c.train_frames, c.seed + 40 + i)
    telemetry.append(require_recorded(record, c.record_gain, sim).telemetry(start=c.settle_frames))
plant = identify_plant(telemetry)
pol = torch.stack([pseudo_open_loop(seq.wfs, seq.y, plant.dm_gain) for seq in telemetry])
scan_seed = c.seed + 3
scored = [c.seed + 2, *(c.seed + 20 + i for i in range(c.scored_realisations - 1))]
integrator = scan_integrator(sim, c.gains, c.loop_frames, scan_seed, c.settle_frames)
print(f"integrator: {integrator['gain']} {integrator['median_rms_nm']:.2f}", flush=True)
modal = scan_modal(sim, pol, plant.dm_gain, c, scan_seed)
print(f"modal: {modal['median_rms_nm']:.2f}", flush=True)
old = scan_lqg(sim, pol, plant.dm_gain, c, scan_seed, orders=(1, 2), scales=(1.0,), coloured=False)
print(f"old lqg: {old['scan']}", flush=True)
new = scan_lqg(sim, pol, plant.dm_gain, c, scan_seed)
print(f"new lqg: AR {new['ar_order']} x {new['noise_scale']} {new['scan']}", flush=True)
controls = {"integrator": IntegratorControl(integrator["gain"]),
            "modal": TorchControl(modal["controller"], sim.delay_frames),
            "lqg_old": TorchControl(old["controller"], sim.delay_frames),
            "lqg_new": TorchControl(new["controller"], sim.delay_frames)}
results = {}
for name, control in controls.items():
    medians = [run_closed_loop(sim, control, c.loop_frames, seed).metrics(c.settle_frames).median_rms_nm
               for seed in scored]
    results[name] = {"realisations_median_rms_nm": medians,
                     "mean_of_realisations_nm": None if None in medians else float(np.mean(medians))}
    print(f"{name}: {medians}", flush=True)
out = {"command": "OMP_NUM_THREADS=1 PYTHONPATH=. python experiments/interop/lqg_small/run.py "
                  "experiments/interop/lqg_small/summary.json",
       "simulator": sim.describe(), "loop_frames": c.loop_frames, "settle_frames": c.settle_frames,
       "recordings": {"sequences": c.train_sequences, "frames": c.train_frames, "record_gain": c.record_gain,
                      "dither_nm": c.dither_nm, "seeds": [c.seed + 40 + i for i in range(c.train_sequences)]},
       "identified": {"dm_gain": plant.dm_gain, "wfs_noise_nm": plant.wfs_noise_nm},
       "scan_seed": scan_seed, "scored_seeds": scored,
       "integrator_scan": {"gain": integrator["gain"], "scan": {str(g): v for g, v in integrator["scan"].items()}},
       "modal_scan": {"gain_margin": modal["gain_margin"], "scan": modal["scan"]},
       "lqg_old_scan": {"ar_order": old["ar_order"], "scan": old["scan"]},
       "lqg_new_scan": {key: new[key] for key in ("ar_order", "noise_scale", "noise_covariance", "scan")},
       "contenders": results, "seconds_loaded_machine": round(time.time() - started)}
with open(sys.argv[1], "w") as f:
    json.dump(out, f, indent=1)
