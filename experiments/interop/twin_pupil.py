"""The anti-aliasing EOF trained in eofnn's twin with OOPAO's own pupil (issue 30), at the 40 x 40 points of `run.sh
oopao_aa` (8 m, 20 m/s, DM applying 2x, I = 8 or 10): OOPAO's loop recorded and identified as there, the filter
trained as `--eofnn-trained` trains it (54000 + 10800 frames in 9 sequences) at each twin seed given, but in a twin
whose pupil is OOPAO's (`eofnn_trained(pupil="oopao")`: the lit pupil inside the DM's last actuators, all 1353 of
OOPAO's actuators, its subapertures at least half lit, the partly lit ones measuring their lit area's mean gradient),
carried over and scored with its raw contrast on the same three realisations as the page's run (whose twin has the
grid's pupil), warmed up with the integrator gain that run scanned. Writes
experiments/runs/interop/twin_pupil/m<I>/twin_pupil.json (seeds already there are kept: each is bit-for-bit the
same when run again); the page reads it beside the run.

    OMP_NUM_THREADS=1 .venv/bin/python experiments/interop/twin_pupil.py 8 0 1 2   # magnitude, then twin seeds
"""

from __future__ import annotations

import json
import sys
import time

from m8_point import RUNS, aa_point

from eofnn.interop.loop import FilterControl
from eofnn.outputs import write_text_atomic
from eofnn.studies.antialias import record_with_truth, score
from eofnn.studies.transfer import eofnn_trained
from eofnn.training.identify import identify_plant


def main(magnitude: int, seeds: list[int]) -> None:
    gain, scored, sim, config = aa_point(magnitude)
    path = RUNS / "twin_pupil" / f"m{magnitude}" / "twin_pupil.json"
    out = json.loads(path.read_text()) if path.is_file() else {"seeds": {}}
    started = time.time()
    plant = identify_plant(record_with_truth(sim, config))
    print(f"identified gain {plant.dm_gain:.4f}, noise {plant.wfs_noise_nm:.1f} nm", flush=True)
    for seed in seeds:
        runtime, info = eofnn_trained(54000, 10800, seed=seed, sequences=9, pupil="oopao")(sim, plant)
        conditions = info.pop("conditions", None)
        result = score(sim, lambda name, runtime=runtime, conditions=conditions: FilterControl(
                           runtime, gain, config.warmup_frames, conditions=conditions),
                       "eof_eofnn_pupil", scored, config)
        print(f"twin seed {seed}: alpha {info['alpha']:.3g}, {info['matched']} actuators matched, {info['held']} "
              "holding; residual per realisation " + ", ".join(
                  "diverged" if v is None else f"{v:.2f}" for v in result["realisations_median_rms_nm"]) + " nm",
              flush=True)
        out["seeds"][str(seed)] = {"fit": info, "contender": result}
    out.update(command=f"python experiments/interop/twin_pupil.py {magnitude} " + " ".join(
        sorted(out["seeds"], key=int)), magnitude=magnitude, scored_seeds=scored, warmup_gain=gain,
        identified={"dm_gain": plant.dm_gain, "wfs_noise_nm": plant.wfs_noise_nm},
        seconds=round(time.time() - started, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(out, indent=1))


if __name__ == "__main__":
    bad = [a for a in sys.argv[1:] if not a.isdigit()]
    if bad:
        sys.exit(f"{bad[0]!r} is not a whole number: give the magnitude (8 or 10), then twin seeds (0, 1, ...)")
    args = [int(a) for a in sys.argv[1:]]
    main(args[0] if args else 8, args[1:] or [0])
