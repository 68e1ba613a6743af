#!/usr/bin/env bash
# Regenerate experiments/: the study's reproduction and its design sweeps, the realistic comparison, the
# closed-loop EOF study, the robustness maps, vibrations and online adaptation; then rewrite
# experiments/README.md from their result files. Well over four hours on 2 cores (the fair contest of section 2 took
# 1 h 40 min on a heavily loaded machine, its alpha check 31 minutes, the MLP budget check 36 and the paper-gap runs
# 10 each on a shared machine; section 2c's moonshot 1 h 8 min; the ELT runs 1.5 and 6.5 minutes, the interop runs
# about 30, the noise-aware fits about 60; the rest about 40). Run after scripts/setup.sh.
# Every sweep is resumable: rerun this script after an interruption and finished points are kept.
#
# Inputs are committed: configs/*.yaml and experiments/{fair,adaptive,sweeps}/*.yaml. Every raw output (compare and
# sweep folders, per-point records, checkpoints, time series) goes under the ignored experiments/runs/<name>/; the
# last step (make_report.py --collect) writes the committed summaries (experiments/<name>/summary.json), copies the
# figures and the runs' own pages (results.md, pareto.md) beside them, and rewrites experiments/README.md.
set -euo pipefail
cd "$(dirname "$0")/.."
eofnn=.venv/bin/eofnn
x=experiments
r=$x/runs
# 1. The study's Figure 3 on its own turbulence (HCIPy pupil layer), and its design choices for open-loop EOF.
$eofnn compare --config configs/paper.yaml --out $r/paper --overwrite true
for grid in alpha history frames; do
  $eofnn sweep --config $x/sweeps/base_ol_eof.yaml --grid $x/sweeps/grid_$grid.yaml --out $r/sweeps/$grid --workers 2
done
# 2. The fair contest: exact frozen flow through each subaperture, two layers, WFS noise 0, 1 and 3 nm; every
#    contender tuned on validation data, classical baselines beside the predictors, performance beside robustness;
#    and alpha: auto against the best fixed alpha on the test stream.
$eofnn compare --config configs/realistic_study.yaml --out $r/realistic --overwrite true --pareto noise_1 \
  --simulated_margins '[noise_1]'
$eofnn compare --config $x/fair/alpha_auto.yaml --out $r/fair/alpha_auto --overwrite true
#    Are the MLP rows limited by their 3 epochs? And the study's MLP gap under the same tuning, on HCIPy's layer and
#    on exact frozen flow of the same layer (point samples; subapertures).
$eofnn compare --config $x/fair/mlp_budget.yaml --out $r/fair/mlp_budget --overwrite true
$eofnn compare --config $x/fair/paper_gap.yaml --out $r/fair/paper_gap/hcipy --overwrite true
$eofnn compare --config $x/fair/paper_gap.yaml --scenario.atmosphere.model exact --scenario.atmosphere.kernel point \
  --out $r/fair/paper_gap/exact --overwrite true
$eofnn compare --config $x/fair/paper_gap.yaml --scenario.atmosphere.model exact \
  --out $r/fair/paper_gap/exact_subaperture --overwrite true
# 2b. The flagship (the README's first command): extreme AO through eofnn's Shack-Hartmann, the tuned classical side
#     (best-gain integrator, modal integrator, LQG with its AR order) against the anti-aliasing EOF and its guard.
$eofnn compare --config configs/flagship_sh.yaml --out $r/flagship --overwrite true
#     The main job through a Shack-Hartmann (photon noise, R = 8), beside the same job through the zonal sensor.
$eofnn compare --config configs/realistic_small.yaml --out $r/realistic_small --overwrite true
$eofnn compare --config configs/realistic_sh.yaml --out $r/realistic_sh --overwrite true
#    Structure before nonlinearity through the Shack-Hartmann, the anti-aliasing predictors among the rows.
$eofnn compare --config $x/fair/structure_sh.yaml --out $r/fair/structure_sh --overwrite true
# 2c. Robust by design: the best predictor stable over DM gain [0.8, 1.25] against the best tuned classical
#     controller; plant-range and loop-trained filters on a small loop; the coupled analysis against bisection.
$eofnn compare --config $x/fair/moonshot.yaml --out $r/fair/moonshot --overwrite true --pareto noise_1
$eofnn compare --config configs/through_loop_small.yaml --out $r/through_loop/noisy --overwrite true
$eofnn compare --config configs/through_loop_small.yaml --scenario.plant.wfs_noise_nm 0 \
  --out $r/through_loop/noise_free --overwrite true
.venv/bin/python $x/coupled_margins.py --out $r/coupled_margins/realistic_10.json
# 2d. Where prediction pays through a real sensor: wind speed x guide-star magnitude on eofnn's Shack-Hartmann loop.
$eofnn sweep --config $x/where/base_sh.yaml --grid $x/where/grid.yaml --out $r/where/sh --workers 2 --overwrite true
$eofnn compare --config $x/where/check_v5.yaml --out $r/where/check_v5 --overwrite true
$eofnn compare --config $x/where/check_v20.yaml --out $r/where/check_v20_m8 --overwrite true
$eofnn compare --config $x/where/check_v20.yaml --scenario.sensor.detector.magnitude 10 --out $r/where/check_v20_m10 \
  --overwrite true
$eofnn compare --config $x/where/check_pfc.yaml --out $r/where/check_pfc --overwrite true
# Where in spatial frequency the anti-aliasing EOF gains (the map's 20 m/s, R = 8 point), and its halo at 10 µm.
$eofnn compare --config $x/where/check_space.yaml --out $r/where/check_space --overwrite true
$eofnn compare --config $x/where/check_space.yaml --evaluation.strehl_wavelength_m 1.0e-5 \
  --out $r/where/check_space_10um --overwrite true
$eofnn sweep --config $x/where/check_space.yaml --grid $x/where/grid.yaml --out $r/where/space --workers 2 --overwrite true
# The oracle's share (eta) over wind speed x seeing (r0 6 and 15 cm at 500 nm), R = 8, the oracle in the contest.
$eofnn sweep --config $x/where/eta_sh.yaml --grid $x/where/eta_grid.yaml --out $r/where/eta --workers 1 --overwrite true
# 3. The study's open question in the realistic scenario: closed-loop EOF against history x training x alpha.
for kind in cl ol; do
  $eofnn sweep --config $x/sweeps/base_realistic_${kind}_eof.yaml --grid $x/sweeps/grid_realistic_${kind}_eof.yaml \
    --out $r/sweeps/realistic_${kind}_eof --workers 2
done
# 4. Robustness maps of the controllers made for the nominal plant, with their analytic margins.
linear='{"integrator": {"controller": "integrator", "gains": [0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95], "refine_rounds": 0, "data": {"frames": 1500}},
  "ol_eof": {"history_length": 4, "optimization": {"alpha": 1.0e-6}, "data": {"frames": 6000, "val_frames": 1000, "sequence_frames": 6000}},
  "cl_eof": {"history": "closed_loop", "history_length": 5, "optimization": {"alpha": 1.0e-6},
             "data": {"frames": 6000, "val_frames": 1000, "sequence_frames": 6000, "integrator_gain": 0.4, "dither_nm": 10.0, "refit_rounds": 1}}}'
gains='{"dm_gain": [0.5, 0.7, 0.9, 1.0, 1.1, 1.3, 1.5, 2.0, 3.0]}'
$eofnn compare --config configs/realistic_small.yaml --scenarios '{"nominal": {}}' --predictors "$linear" \
  --robustness "$gains" --out $r/robustness_realistic --overwrite true
$eofnn compare --config configs/realistic_small.yaml --scenarios '{"nominal": {}}' --predictors "$linear" \
  --robustness '{"misregistration_x": [0.0, 0.05, 0.1, 0.2, 0.3, 0.5]}' \
  --out $r/robustness_realistic_misregistration --overwrite true
$eofnn compare --config configs/paper_small.yaml --scenarios '{"nominal": {}}' --predictors "$linear" \
  --predictors.ol_eof.optimization.alpha 1.0e-12 --predictors.cl_eof.optimization.alpha 1.0e-12 \
  --robustness "$gains" --out $r/robustness_study --overwrite true
# 5. Vibrations, and online adaptation under changing conditions (their pages: vibrations/, ADAPTIVE.md).
$eofnn compare --config configs/vibrations.yaml --out $r/vibrations --overwrite true
#    The reference filter of wind_speed.yaml: the same EOF fitted in the post-change scenario.
$eofnn fit --scenario $x/adaptive/wind_speed_after.yaml --predictor.history open_loop \
  --predictor.history_length 6 --predictor.data '{frames: 5000, val_frames: 500, sequence_frames: 2500}' \
  --predictor.optimization.alpha 1.0e-9 --out $r/adaptive/retrained_20mps.ckpt --overwrite true
for run in wind_speed wind_turn dm_gain_drift; do
  $eofnn compare --config $x/adaptive/$run.yaml --out $r/adaptive/$run --overwrite true
done
$eofnn compare --config $x/adaptive/dm_gain_drift.yaml --scenario.plant.dm_gain_drift.to 2.0 \
  --out $r/adaptive/dm_gain_drift_2.0 --overwrite true
# 6. Learning from telemetry alone against simulator truth (its page: telemetry.md), and noise-aware fits from
#    telemetry (their page: noise_aware/README.md; about an hour).
.venv/bin/python $x/telemetry_training.py
bash $x/noise_aware/run.sh
# 7. An ELT-class loop (5024 actuators, three non-lattice layers), every predictor from telemetry alone.
$eofnn compare --config configs/elt_small.yaml --out $r/elt_small --overwrite true
$eofnn compare --config configs/elt_scao.yaml --out $r/elt --overwrite true --simulated_margins '[nominal]'
# 8. eofnn's controllers inside OOPAO's and HCIPy's own loops (about 46 min on 2 cores).
bash $x/interop/run.sh
.venv/bin/python $x/make_report.py --collect
