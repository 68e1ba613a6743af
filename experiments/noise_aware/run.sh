#!/usr/bin/env bash
# Noise-aware fits from telemetry alone (issue 30, item 2): experiments/noise_aware/README.md holds the numbers.
# eofnn's own zonal loop (experiments/noise_aware/scenario.yaml: 16 across, two layers, delay 2) records dithered
# integrator telemetry at 0, 2 and 5 nm of white WFS noise (8000 frames to fit on, 4000 held out); open-loop EOFs
# (4 taps, alpha: auto on the last 1500 frames) are fitted from each file alone (plant and noise identified) with
# optimization.noise_model none, errors_in_variables and per_mode_snr, per actuator and per KL mode; the noise-free
# fits (per actuator and per mode) are also refitted for 2 and 5 nm of deployment noise
# (optimization.noise_at_deployment_nm). The checkpoints run in the closed loop at the noise they are meant for
# (evaluate_*.yaml, 3 realisations) and are replayed on held-out telemetry of that noise. About an hour on 2 busy
# cores. Raw outputs go to experiments/runs/noise_aware/.
set -euo pipefail
cd "$(dirname "$0")/../.."
eofnn=${EOFNN:-.venv/bin/eofnn}
x=experiments/noise_aware
r=experiments/runs/noise_aware
mkdir -p $r/ckpt $r/replay
for n in 0 2 5; do
  [ -f $r/tel_${n}nm.npz ] || $eofnn simulate --scenario $x/scenario.yaml --scenario.plant.wfs_noise_nm $n.0 \
    --predictor.controller dithered_integrator --predictor.gain 0.4 --predictor.data.dither_nm 10.0 \
    --frames 8000 --seed 1 --out $r/tel_${n}nm.npz
  [ -f $r/held_${n}nm.npz ] || $eofnn simulate --scenario $x/scenario.yaml --scenario.plant.wfs_noise_nm $n.0 \
    --predictor.controller dithered_integrator --predictor.gain 0.4 --predictor.data.dither_nm 10.0 \
    --frames 4000 --seed 2 --out $r/held_${n}nm.npz
done
fit() {  # fit NAME TRAINING_NOISE OPTIONS...: one open-loop EOF from telemetry alone
  local name=$1 n=$2
  shift 2
  [ -f $r/ckpt/$name.ckpt ] || $eofnn fit --telemetry "[$r/tel_${n}nm.npz]" --predictor.history_length 4 \
    --predictor.data.val_frames 1500 --out $r/ckpt/$name.ckpt "$@"
}
modal=(--predictor.network "{class_path: eofnn.models.linear.LinearFilter, init_args: {structure: modal}}")
fit t0_none 0
fit t0_eiv 0 --predictor.optimization.noise_model errors_in_variables
fit t0_modal 0 "${modal[@]}"
for n in 2 5; do
  fit t${n}_none $n
  fit t${n}_eiv $n --predictor.optimization.noise_model errors_in_variables
  fit t${n}_snr $n --predictor.optimization.noise_model per_mode_snr
  fit t${n}_modal $n "${modal[@]}"
  fit t${n}_modal_snr $n "${modal[@]}" --predictor.optimization.noise_model per_mode_snr
  fit t0_deploy${n} 0 --predictor.optimization.noise_at_deployment_nm $n.0
  fit t0_modal_deploy${n} 0 "${modal[@]}" --predictor.optimization.noise_at_deployment_nm $n.0
done
for name in 0nm 2nm 5nm modal_deploy; do
  $eofnn evaluate --config $x/evaluate_$name.yaml --out $r/evaluate_$name --overwrite true
done
replay() {  # replay NAME NOISE: a checkpoint on held-out telemetry
  $eofnn replay --checkpoint $r/ckpt/$1.ckpt --telemetry "[$r/held_$2nm.npz]" --settle_frames 100 \
    --out $r/replay/$1_on_$2nm --overwrite true
}
replay t0_none 0
for n in 2 5; do
  for name in t${n}_none t${n}_eiv t${n}_snr t${n}_modal t${n}_modal_snr t0_none t0_deploy${n} t0_modal_deploy${n}; do
    replay $name $n
  done
done
.venv/bin/python $x/summarise.py $r $x/summary.json
