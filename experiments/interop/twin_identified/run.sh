#!/usr/bin/env bash
# The anti-aliasing EOF trained in a twin identified from OOPAO's telemetry alone (examples/oopao_loop.py
# --twin-identified, eofnn/studies/twin_transfer.py), scored in OOPAO's closed loop beside the best classical
# controllers, the same EOF trained on OOPAO's truth (eof_antialias: the gap's far end) and the twin built from
# OOPAO's settings (eof_eofnn, --eofnn-trained: simulator knowledge, a labelled reference row).
#
# Seeds, fixed before any run (the study's seed is 0, AntiAliasConfig.seed):
#   - training recordings (eof_measured, eof_antialias): realisations 40, 41, 42, dither seeds 140, 141, 142;
#   - the integrator's, modal's, LQG's and PFC's tuning and the guard: realisation 3;
#   - scored realisations: 2, 20, 21 (--realisations 3): never used to design or tune anything;
#   - the twin's identification record: realisation 500, dither seed 600 (RECORD_SEED_OFFSET, DITHER_SEED_OFFSET in
#     eofnn/studies/twin_transfer.py), 4000 frames, the first 200 dropped;
#   - both twins' training streams: eofnn seed 0 (9 realisations of 3 x --frames x 1.2 / 9 frames);
#   - OOPAO's photon noise: the realisation's seed + 7.
# Two layers (Cn2 70% at 20 m/s, 30 deg; 30% at 10 m/s, 120 deg, OOPAO's convention), I = 8, photon noise.
# One thread (OOPAO's numbers are bit-for-bit only at a fixed thread count).
set -euo pipefail
cd "$(dirname "$0")/../../.."
PY=${PYTHON:-.venv/bin/python}
what=${1:-all}
run() { OMP_NUM_THREADS=1 $PY examples/oopao_loop.py --photon-noise --magnitude 8 --anti-aliasing --twin-identified \
    --no-oracle --realisations 3 --layers 0.7:20:30,0.3:10:120 "$@"; }
if [ "$what" = all ] || [ "$what" = small ]; then
    # 20 x 20 on 4 m (the OOPAO map's system), 1000 frames per recording.
    run --n-subapertures 20 --diameter 4 --frames 1000 --eofnn-trained --out experiments/runs/interop/twin_identified/small_m8_2layers
fi
if [ "$what" = all ] || [ "$what" = full ]; then
    # The issue's system: 8 m, 40 x 40, rcond 0.075, 2000 frames per recording. Without the settings twin
    # (--eofnn-trained): with it, the first try (2026-12-06) stopped in that twin, whose two layers' exact screens
    # (1.9 GiB each at 40 x 40) found too little memory free on the shared machine.
    run --n-subapertures 40 --diameter 8 --rcond 0.075 --frames 2000 \
        --out experiments/runs/interop/twin_identified/m8_2layers
fi
# After a run: python experiments/interop/twin_identified/gap.py small_m8_2layers m8_2layers (the gap shares from
# metrics.json into experiments/interop/twin_identified/<run>/summary.json, results.md copied beside it).
