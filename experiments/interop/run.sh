#!/usr/bin/env bash
# eofnn's controllers inside OOPAO's and HCIPy's closed loops (docs/interop.md): writes the raw runs
# experiments/runs/interop/<sim>/{metrics.json,results.md}; make_report.py --collect summarises them into
# experiments/interop/<sim>/. Needs the interop extra (bash scripts/setup.sh installs it).
#   - oopao: the issue's system (8 m, 40 x 40 Shack-Hartmann, 1 kHz, two frames, DM applying 2x), 1600 frames per
#     recording, every contender scored on 3 realisations (about 17 min on 2 cores, 2026-12-02);
#   - oopao_aliasing: the error budget (perfect sensor, SH noise-free, SH with photon noise) at 20 x 20 on 4 m
#     (about 9 min);
#   - oopao_map: 20 x 20 on 4 m with photon noise only, at 10 and 20 m/s x I = 8 and 10 (four points);
#   - oopao_aa: the EOF from telemetry, the anti-aliasing EOF (trained on OOPAO's truth, and in eofnn's twin) and the oracle
#     against the integrator, the modal integrator, the LQG and PFC at 8 m, 40 x 40, 20 m/s, I = 8 and 10, and the
#     checks beside them (about 5 h of CPU, one thread per run);
#   - oopao_long: oopao_aa's I = 8 point on 5 realisations of 2000 scored frames, with the MAP reconstructor from
#     telemetry for every contender (about 2 h on one core); oopao_long10: its I = 10 point the same way;
#   - map_small: the anti-aliasing study at 20 x 20 on 4 m, I = 8, 20 m/s, with every contender on the truncated
#     least-squares reconstructor and on the MAP one (--reconstructor map), at rcond 0.15 and 0.02, and on MAP from
#     telemetry (map_telemetry) at 0.15 (about 5 min a run);
#   - pyramid_contest: the contest through OOPAO's modulated pyramid at experiments/pyramid/contest.yaml's system,
#     I = 8 and 10 (about 30 min);
#   - hcipy: 8 m, 40 x 40 phase-projection loop (about 16 min).
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
what=${1:-all}
if [ "$what" = all ] || [ "$what" = oopao ]; then
    $PY examples/oopao_loop.py --n-subapertures 40 --diameter 8 --frames 1600 --rcond 0.075 --realisations 3 \
        --out experiments/runs/interop/oopao
fi
if [ "$what" = all ] || [ "$what" = oopao_aliasing ]; then
    $PY examples/oopao_loop.py --n-subapertures 20 --diameter 4 --frames 2000 --aliasing --realisations 3 \
        --out experiments/runs/interop/oopao_aliasing
fi
if [ "$what" = all ] || [ "$what" = oopao_map ]; then
    # Where prediction pays in OOPAO's loop (the smaller map of issue 30): 20 x 20 on 4 m, photon noise only.
    for wind in 10 20; do
        for mag in 8 10; do
            $PY examples/oopao_loop.py --n-subapertures 20 --diameter 4 --frames 2000 --photon-noise --wind $wind \
                --magnitude $mag --realisations 3 --out experiments/runs/interop/oopao_map/v${wind}_m${mag}
        done
    done
fi
if [ "$what" = all ] || [ "$what" = oopao_aa ]; then
    # The issue's "win" conditions in OOPAO's loop: 8 m, 40 x 40 SH, photon noise, 20 m/s, I = 8 and 10 (wind along
    # the actuator rows), and I = 8 with the wind at 30 degrees; then 20 x 20 on 4 m (the OOPAO map's system) at both
    # directions. The 5 x 5 open-loop EOF fitted on telemetry alone and the anti-aliasing EOF fitted on OOPAO's truth,
    # against the best-gain integrator, the LQG and PFC built from the same telemetry; 3 training sequences of 2000
    # frames, every contender scored on 3 realisations of 1000 frames. About 50 min of CPU per 40 x 40 run.
    # One thread: OOPAO's numbers are bit-for-bit only at a fixed thread count, and these were made with one.
    aa() { OMP_NUM_THREADS=1 $PY examples/oopao_loop.py --frames 2000 --photon-noise --anti-aliasing --wind 20 --realisations 3 "$@"; }
    # Both magnitudes with the strengthened classical side (the modal integrator with optimised gains, PFC's memory
    # scan past its grid's edge and its noise coloured by the reconstructor) and the oracle (trained on OOPAO's truth,
    # 6 taps, 7 x 7, 12 recordings: about 25 min more per run); each predictor's eta.
    aa --n-subapertures 40 --diameter 8 --rcond 0.075 --magnitude 8 --out experiments/runs/interop/oopao_aa/m8
    aa --n-subapertures 40 --diameter 8 --rcond 0.075 --magnitude 10 --out experiments/runs/interop/oopao_aa/m10
    # Both magnitudes also with the anti-aliasing EOF trained in eofnn's own simulation of the system (--eofnn-trained;
    # the page's were run before the modal integrator, PFC's coloured noise and the oracle, all on the same
    # realisations as m8 and m10; the twin sections read them).
    aa --n-subapertures 40 --diameter 8 --rcond 0.075 --magnitude 8 --eofnn-trained --no-oracle \
        --out experiments/runs/interop/oopao_aa/m8_eofnn_trained
    aa --n-subapertures 40 --diameter 8 --rcond 0.075 --magnitude 10 --eofnn-trained --no-oracle \
        --out experiments/runs/interop/oopao_aa/m10_eofnn_trained
    aa --n-subapertures 40 --diameter 8 --rcond 0.075 --magnitude 8 --wind-direction 30 \
        --out experiments/runs/interop/oopao_aa/m8_dir30
    # At 0 degrees (the direction mapped onto eofnn's) also the anti-aliasing EOF trained in eofnn's own simulation,
    # with the twin's pupil its grid's (eof_eofnn) and OOPAO's (eof_eofnn_pupil).
    aa --n-subapertures 20 --diameter 4 --magnitude 8 --eofnn-trained --twin-pupil both \
        --out experiments/runs/interop/oopao_aa/small_m8_dir0
    aa --n-subapertures 20 --diameter 4 --magnitude 8 --wind-direction 30 \
        --out experiments/runs/interop/oopao_aa/small_m8_dir30
    # The same open-loop EOFs on each actuator's own history alone (no neighbourhood).
    aa --n-subapertures 20 --diameter 4 --magnitude 8 --radius 0.5 --out experiments/runs/interop/oopao_aa/small_m8_dir0_own
    # The eofnn-trained EOF with its twin at its own photon noise and on all its modes (what --eofnn-trained did
    # before its noise was matched in OOPAO's command units and its modes to OOPAO's reconstructor's).
    aa --n-subapertures 20 --diameter 4 --magnitude 8 --eofnn-trained --own-noise --all-modes \
        --out experiments/runs/interop/oopao_aa/small_m8_dir0_twin_own
    # The eofnn-trained and the OOPAO-truth-trained filters side by side: their responses to static POL patterns.
    OMP_NUM_THREADS=1 $PY experiments/interop/transfer_diagnostic.py
    # The eofnn-trained EOF at I = 8 with its twin trained at seeds 1 and 2 (the page's run is seed 0): reads m8's run
    # (its integrator gain and scored realisations).
    OMP_NUM_THREADS=1 $PY experiments/interop/twin_seeds.py 1 2
    # Where the eofnn-trained EOF loses at I = 8: the rim or the interior (offline, and in the loop spliced with the
    # truth-trained filter): reads m8's run.
    OMP_NUM_THREADS=1 $PY experiments/interop/rim_diagnostic.py
    # The eofnn-trained EOF with OOPAO's pupil in its twin (all of OOPAO's actuators and its partly lit subapertures),
    # at I = 8 and 10 over three training sets of the twin each: reads m8's and m10's runs.
    OMP_NUM_THREADS=1 $PY experiments/interop/twin_pupil.py 8 0 1 2
    OMP_NUM_THREADS=1 $PY experiments/interop/twin_pupil.py 10 0 1 2
fi
if [ "$what" = all ] || [ "$what" = oopao_long ]; then
    # The I = 8 headline again on 5 realisations of 2000 scored frames (--scored-frames; the tuning runs stay 1000
    # frames), every contender on the MAP reconstructor built from the loop's own recording (map_telemetry, its weight
    # scanned on the scan realisation), the LQG's model and noise scale scanned, the oracle beside them. Scored
    # realisations 2, 20, 21, 22, 23 (the first three longer runs of the realisations m8 scored on 1000 frames).
    OMP_NUM_THREADS=1 $PY examples/oopao_loop.py --frames 2000 --photon-noise --anti-aliasing --wind 20 --realisations 5 \
        --n-subapertures 40 --diameter 8 --rcond 0.075 --magnitude 8 --scored-frames 2000 --reconstructor map_telemetry \
        --out experiments/runs/interop/oopao_aa/m8_long
fi
if [ "$what" = all ] || [ "$what" = oopao_long10 ]; then
    # The I = 10 headline the same way (5 realisations of 2000 scored frames, MAP from telemetry for all, the oracle).
    OMP_NUM_THREADS=1 $PY examples/oopao_loop.py --frames 2000 --photon-noise --anti-aliasing --wind 20 --realisations 5 \
        --n-subapertures 40 --diameter 8 --rcond 0.075 --magnitude 10 --scored-frames 2000 --reconstructor map_telemetry \
        --out experiments/runs/interop/oopao_aa/m10_long
fi
if [ "$what" = all ] || [ "$what" = map_small ]; then
    # Every contender (integrator, modal integrator, LQG, PFC, the EOFs) on one reconstructor, the loop's: the
    # truncated least squares or MAP (r0, L0 and the photon noise from the simulator; its factor scanned on the scan
    # realisation); at rcond 0.15 (the default) and 0.02 (more modes controlled: the MAP's prior regularises them).
    for rcond in 0.15 0.02; do
        for rec in least_squares map; do
            sfx=$([ "$rcond" = 0.15 ] && echo "" || echo "_rcond$rcond")
            OMP_NUM_THREADS=1 $PY examples/oopao_loop.py --n-subapertures 20 --diameter 4 --frames 2000 --photon-noise \
                --anti-aliasing --wind 20 --realisations 2 --magnitude 8 --no-oracle --rcond $rcond --reconstructor $rec \
                --out experiments/runs/interop/map_small/$rec$sfx
        done
    done
    # MAP with the turbulence and the noise estimated from the loop's own telemetry (no simulator setting).
    OMP_NUM_THREADS=1 $PY examples/oopao_loop.py --n-subapertures 20 --diameter 4 --frames 2000 --photon-noise \
        --anti-aliasing --wind 20 --realisations 2 --magnitude 8 --no-oracle --reconstructor map_telemetry \
        --out experiments/runs/interop/map_small/map_telemetry
fi
if [ "$what" = all ] || [ "$what" = pyramid_contest ]; then
    # The contest through OOPAO's modulated pyramid (experiments/pyramid/README.md, "The contest in OOPAO's loop"):
    # experiments/pyramid/contest.yaml's system (2 m, 10 x 10 at 0.2 m, 20 m/s, modulation 3 lambda/D) at I = 8 and
    # 10, the anti-aliasing study's contenders (no twin: it is a Shack-Hartmann); 3 training sequences of 1000 frames,
    # every contender scored on 3 realisations of 500 (about 15 min each on a loaded 2-core machine, 2026-12-07).
    for mag in 8 10; do
        OMP_NUM_THREADS=1 $PY examples/oopao_loop.py --sensor pyramid --modulation 3 --photon-noise --anti-aliasing \
            --wind 20 --n-subapertures 10 --diameter 2 --magnitude $mag --frames 1000 --realisations 3 \
            --out experiments/runs/interop/pyramid_contest/m$mag
    done
fi
if [ "$what" = all ] || [ "$what" = hcipy ]; then
    $PY examples/hcipy_interop.py --n-subapertures 40 --diameter 8 --frames 2000 --realisations 3 \
        --out experiments/runs/interop/hcipy
fi
