"""How much the anti-aliasing EOF trained in eofnn's twin moves with the twin's own training realisation (issue 30):
OOPAO's 40 x 40 loop of `run.sh oopao_aa`'s m8 point (8 m, I = 8, 20 m/s, DM applying 2x) recorded and identified as
there, the filter trained in the twin at other seeds (`eofnn_trained(seed=...)`, 54000 + 10800 frames in 9
sequences, as `--eofnn-trained` trains it at `--frames 2000`), carried over and scored on the same three realisations
as the page's run (twin seed 0), warmed up with the integrator gain that run scanned. Writes
experiments/runs/interop/twin_seeds/twin_seeds.json; the page reads it beside the m8 run.

    OMP_NUM_THREADS=1 .venv/bin/python experiments/interop/twin_seeds.py 1 2    # about 5 min + 9 min per seed
"""

from __future__ import annotations

import json
import sys

from m8_point import RUNS, m8_point

from eofnn.interop.loop import FilterControl, run_closed_loop
from eofnn.outputs import write_text_atomic
from eofnn.studies.antialias import record_with_truth
from eofnn.studies.transfer import eofnn_trained
from eofnn.training.identify import identify_plant


def main(seeds: list[int]) -> None:
    gain, scored, sim, config = m8_point()
    plant = identify_plant(record_with_truth(sim, config))
    print(f"identified gain {plant.dm_gain:.4f}, noise {plant.wfs_noise_nm:.1f} nm", flush=True)
    out = {"command": "python experiments/interop/twin_seeds.py " + " ".join(map(str, seeds)), "scored_seeds": scored,
           "warmup_gain": gain, "identified": {"dm_gain": plant.dm_gain, "wfs_noise_nm": plant.wfs_noise_nm},
           "seeds": {}}
    for seed in seeds:
        runtime, info = eofnn_trained(54000, 10800, seed=seed, sequences=9)(sim, plant)
        rms = [run_closed_loop(sim, FilterControl(runtime, gain, config.warmup_frames), config.loop_frames, s)
               .metrics(config.settle_frames).median_rms_nm for s in scored]
        out["seeds"][str(seed)] = {"alpha": info["alpha"], "realisations_median_rms_nm": rms}
        print(f"twin seed {seed}: alpha {info['alpha']:.3g}, residual per realisation "
              f"{', '.join('diverged' if v is None else f'{v:.2f}' for v in rms)} nm", flush=True)
    (RUNS / "twin_seeds").mkdir(parents=True, exist_ok=True)
    write_text_atomic(RUNS / "twin_seeds" / "twin_seeds.json", json.dumps(out, indent=1))


if __name__ == "__main__":
    main([int(s) for s in sys.argv[1:]] or [1, 2])
