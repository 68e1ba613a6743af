"""Why identification overestimates the DM gain with OOPAO's pyramid under photon noise (examples/oopao_loop.py
--small --sensor pyramid --photon-noise --magnitude 10), measured, not guessed.

It records the study's telemetry (the integrator at gain 0.25, 10 nm of white dither, 1000 frames, 300 settling,
seed 0, wind 20 m/s: ``eofnn.studies.study.run_study``'s recording), identifies the plant from it, and beside that measures on
the recorded loop's own residual maps (every ``--every`` frames after settling), OOPAO's pyramid noise-free:

* ``G``: the response matrix ``R D_res`` (actuator space, per unit command, DM gain 1) by push-pull of every
  actuator (1 nm) about each residual, averaged over the residuals;
* ``diag``: its mean diagonal on the seen modes, ``tr(P G P) / tr(P)`` (what ``measure_sensor_gain``'s white random
  probe estimates: the "optical gain" the example reports);
* ``kernel``: the 3 x 3 neighbourhood row sums of ``G`` over interior actuators (what identification's local
  regression estimates: the DM gain is the pooled 3 x 3 coupling sum), both on ``G`` and on ``G P``
  (the loop only ever applies projected commands);
* the optical gain per seen mode (``<P_m, G P_m>``, low to high order).

Simulator knowledge (a diagnostic, not an eofnn input).

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python experiments/pyramid/photon_noise.py --photon-noise \
        --magnitude 10 --out experiments/pyramid/photon_noise/summary.json
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from eofnn.interop.loop import IntegratorControl, run_closed_loop
from eofnn.interop.oopao import OopaoLoop, measure_sensor_gain
from eofnn.interop.oopao_pyramid import pyramid_signals
from eofnn.training.identify import identify_plant


def response_matrix(sim, residual_maps_nm, amplitude_nm=1.0):
    """``(R, K, K)``: ``R @ (s(res + a e_j) - s(res - a e_j)) / 2a`` per actuator ``j`` (noise-free pyramid)."""
    res, to_rad = sim.tel.resolution, 2 * np.pi / (float(sim.ngs.wavelength) * 1e9)
    shapes = np.asarray(sim.dm.modes, dtype=np.float64).T.reshape(-1, res, res) * np.asarray(sim.tel.pupil, float)
    noise, sim.wfs.cam.photonNoise = sim.wfs.cam.photonNoise, False
    out = []
    try:
        for around in residual_maps_nm:
            push = np.concatenate([around + amplitude_nm * shapes, around - amplitude_nm * shapes]) * to_rad
            s = pyramid_signals(sim.wfs, push)
            out.append(sim.reconstructor @ ((s[:len(shapes)] - s[len(shapes):]) / (2 * amplitude_nm)).T)
    finally:
        sim.wfs.cam.photonNoise = noise
    return np.asarray(out)


def kernel_sums(g, positions, pitch):
    """Row sums of ``g`` over each actuator's 3 x 3 neighbourhood, for actuators whose 8 neighbours all exist."""
    d = np.abs(positions[:, None, :] - positions[None, :, :]) / pitch
    near = (d.max(-1) < 1.5)
    interior = near.sum(1) == 9
    return np.array([g[k, near[k]].sum() for k in np.flatnonzero(interior)]), interior


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--photon-noise", action="store_true")
    p.add_argument("--magnitude", type=float, default=10.0)
    p.add_argument("--frames", type=int, default=1000)
    p.add_argument("--wind", type=float, default=20.0, help="m/s (the examples' default)")
    p.add_argument("--every", type=int, default=50, help="frames between residual maps probed")
    p.add_argument("--out", default=None)
    a = p.parse_args()
    t0 = time.time()
    sim = OopaoLoop(10, 2.0, sensor="pyramid", photon_noise=a.photon_noise, magnitude=a.magnitude, dm_gain=2.0,
                    wind_speed_mps=a.wind)
    maps = []
    res = sim.tel.resolution

    def keep(n, s):
        if n >= 300 and (n - 300) % a.every == 0:
            full = np.zeros((res, res))
            full[s.pupil_mask] = s.residual_opd_nm()
            maps.append(full)

    rec = run_closed_loop(sim, IntegratorControl(0.25, 10.0, seed=100), a.frames, 0, observers=[keep])
    plant = identify_plant(rec.telemetry(start=300))
    rms = rec.metrics(300).summary()["median_rms_nm"]
    print(f"recorded: median residual {rms:.1f} nm; identified DM gain {plant.dm_gain:.4f} +- {plant.dm_gain_se:.4f}, "
          f"noise {plant.wfs_noise_nm:.2f} nm ({time.time() - t0:.0f} s)", flush=True)
    probe = measure_sensor_gain(sim, 0.25, a.frames, 0, dither_nm=10.0)
    print(f"measure_sensor_gain (white 5 nm probes, noise as set): {probe['mean']:.4f} +- {probe['se']:.4f} "
          f"-> 2 x = {2 * probe['mean']:.4f} ({time.time() - t0:.0f} s)", flush=True)
    clean = measure_sensor_gain(sim, 0.25, a.frames, 0, dither_nm=10.0, noise_free=True)
    print(f"measure_sensor_gain, the probes read noise-free (the same loop): {clean['mean']:.4f} +- {clean['se']:.4f} "
          f"-> 2 x = {2 * clean['mean']:.4f} ({time.time() - t0:.0f} s)", flush=True)
    g_all = response_matrix(sim, maps)
    g_flat = response_matrix(sim, [np.zeros((res, res))])[0]
    proj = sim.controlled_modes @ sim.controlled_modes.T
    out = {"settings": vars(a), "median_residual_nm": rms, "identified_dm_gain": plant.dm_gain,
           "identified_dm_gain_se": plant.dm_gain_se, "identified_noise_nm": plant.wfs_noise_nm,
           "identified_pattern_sum_interior_mean_actuator_gain": float(np.mean(plant.actuator_gains)),
           "probe_gain": probe, "probe_gain_noise_free": clean,
           "n_residual_maps": len(maps)}
    pitch = float(np.min(np.linalg.norm(sim.positions_m[1:] - sim.positions_m[0], axis=1)))
    for name, g in (("flat", g_flat), ("residual", g_all.mean(0))):
        diag = float(np.trace(proj @ g @ proj) / np.trace(proj))
        ks, interior = kernel_sums(g, sim.positions_m, pitch)
        ksp, _ = kernel_sums(g @ proj, sim.positions_m, pitch)
        modes = sim.controlled_modes
        per_mode = np.einsum("km,kl,lm->m", modes, g, modes)
        out[name] = {"diag": diag, "kernel_sum": float(ks.mean()), "kernel_sum_projected": float(ksp.mean()),
                     "n_interior": int(interior.sum()), "per_mode": per_mode.tolist()}
        print(f"[{name}] diag {diag:.4f}; 3x3 kernel sum {ks.mean():.4f} (G P: {ksp.mean():.4f}, {interior.sum()} "
              f"interior); per mode: first 5 {np.round(per_mode[:5], 3)}, deciles "
              f"{np.round([per_mode[int(q * (len(per_mode) - 1))] for q in (0, .25, .5, .75, 1)], 3)}", flush=True)
    ratio = out["residual"]["per_mode"]
    out["og_per_mode_relative_to_flat"] = (np.asarray(ratio) / np.asarray(out["flat"]["per_mode"])).tolist()
    og = np.asarray(out["og_per_mode_relative_to_flat"])
    print(f"OG per mode (residual / flat): min {og.min():.3f} median {np.median(og):.3f} max {og.max():.3f}; "
          f"first 5 {np.round(og[:5], 3)}; mean {og.mean():.3f}  ({time.time() - t0:.0f} s)")
    if a.out:
        with open(a.out, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
