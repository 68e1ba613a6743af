"""How much the anti-aliasing EOF trained in eofnn's twin moves with the twin's own training realisation (issue 30):
OOPAO's 40 x 40 loop of `run.sh oopao_aa`'s m8 point (8 m, I = 8, 20 m/s, DM applying 2x) recorded and identified as
there, the filter trained in the twin at other seeds (`eofnn_trained(seed=...)`, 18000 + 3600 frames), carried
over and scored on the same three realisations as the page's run (seed 0), with the scanned integrator's gain 0.3.

    OMP_NUM_THREADS=1 .venv/bin/python experiments/interop/twin_seeds.py 1 2    # about 5 min + 4 min per seed
"""

from __future__ import annotations

import sys

import numpy as np

from eofnn.interop.antialias import AntiAliasConfig, record_with_truth
from eofnn.interop.loop import FilterControl, run_closed_loop
from eofnn.interop.oopao import OopaoLoop
from eofnn.interop.transfer import eofnn_trained
from eofnn.training.identify import identify_plant


def main(seeds: list[int]) -> None:
    sim = OopaoLoop(40, 8.0, photon_noise=True, magnitude=8.0, dm_gain=2.0, wind_speed_mps=20.0, rcond=0.075)
    config = AntiAliasConfig(train_frames=2000, val_frames=400, loop_frames=1000, settle_frames=200, warmup_frames=100)
    plant = identify_plant(record_with_truth(sim, config))
    print(f"identified gain {plant.dm_gain:.4f}, noise {plant.wfs_noise_nm:.1f} nm", flush=True)
    for seed in seeds:
        runtime, info = eofnn_trained(18000, 3600, seed=seed)(sim, plant)
        rms = [run_closed_loop(sim, FilterControl(runtime, 0.3, 100), 1000, s).metrics(200).median_rms_nm
               for s in (2, 20, 21)]
        print(f"twin seed {seed}: alpha {info['alpha']:.3g}, residual per realisation "
              f"{', '.join(f'{v:.2f}' for v in rms)} nm, mean {np.mean(rms):.2f} nm", flush=True)


if __name__ == "__main__":
    main([int(s) for s in sys.argv[1:]] or [1, 2])
