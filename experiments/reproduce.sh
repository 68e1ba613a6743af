#!/usr/bin/env bash
# Regenerate the reproduction of the reference study: run configs/paper.yaml, the design-choice sweeps, and
# rewrite experiments/README.md from their metrics. About 20 minutes on 2 cores. Run after scripts/setup.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
eofnn=.venv/bin/eofnn
$eofnn compare --config configs/paper.yaml --out experiments/paper --overwrite true
# A 40 Hz tip vibration in the realistic telescope: integrator against open-loop EOF (about 2 minutes).
$eofnn compare --config configs/vibrations.yaml --out experiments/vibrations --overwrite true
# Design choices, open-loop EOF in the nominal scenario (see experiments/README.md).
only_ol='{"uncorrected": {"controller": "uncorrected"}, "ol_eof": {"history_length": 4, "optimization": {"alpha": 1.0e-12}, "train_in": "nominal", "data": {"frames": 20000}}}'
for alpha in 1.0e-6 1.0e-9 1.0e-12 1.0e-14; do
  $eofnn compare --config configs/paper.yaml --scenarios '{"nominal": {}}' --predictors "$only_ol" \
    --predictors.ol_eof.optimization.alpha $alpha --out experiments/sweeps/alpha_$alpha --overwrite true
done
for p in 2 4 8 16; do
  $eofnn compare --config configs/paper.yaml --scenarios '{"nominal": {}}' --predictors "$only_ol" \
    --predictors.ol_eof.history_length $p --out experiments/sweeps/history_$p --overwrite true
done
for frames in 2000 6000 20000; do
  $eofnn compare --config configs/paper.yaml --scenarios '{"nominal": {}}' --predictors "$only_ol" \
    --predictors.ol_eof.data.frames $frames --out experiments/sweeps/frames_$frames --overwrite true
done
.venv/bin/python experiments/make_report.py
