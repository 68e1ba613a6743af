"""Why ``eofnn twin`` found r0 +12% on OOPAO's 40 x 40 record (issue 46), measured on that record.

The record: experiments/interop/twin_identified/run.sh full's system (8 m, OOPAO's diffractive Shack-Hartmann of 40 x
40 subapertures with photon noise at I = 8, rcond 0.075; two layers, 70% at 20 m/s at OOPAO's 30 deg and 30% at 10
m/s at 120 deg; r0 0.15 m, L0 25 m) recorded as the transfer records it (``twin_transfer.record_loop``: realisation
500, dithered integrator at gain 0.25, 4000 frames, the first 200 dropped), with OOPAO's DM gain 1 (the study's DM
gain of 2 is a deliberate plant error; here the DM is as calibrated, so the identified product is the sensor's).

Three measurements:
1. ``eofnn twin --command_unit peak`` on it, as a user runs it;
2. the sensor's optical gain in the same loop, from OOPAO's truth (``measure_sensor_gain``: probes pushed and pulled
   on the loop's residual; noise-free reads and noisy ones): simulator knowledge, to explain, not to identify;
3. r0 refitted against each outer scale's reference alone (20, 25 and 40 m; 25 is OOPAO's, simulator knowledge), with
   the POL as read and divided by the optical gain (the probes' and the identified product).

    OMP_NUM_THREADS=1 .venv/bin/python experiments/interop/twin_r0_40.py     # about 25 min on one core (10 to refit)

Raw files go to experiments/runs/interop/twin_r0_40/ (reused when there); the summary to
experiments/interop/twin_r0_40/summary.json.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

import eofnn.training.twin as twin
import eofnn.training.twin_seeing as seeing
from eofnn.telemetry.record import Telemetry

ROOT = Path(__file__).resolve().parents[2]
RUNS = ROOT / "experiments" / "runs" / "interop" / "twin_r0_40"
OUT = ROOT / "experiments" / "interop" / "twin_r0_40"
LAYERS = [(0.7, 20.0, 30.0), (0.3, 10.0, 120.0)]
R0_M, OUTER_SCALES_M = 0.15, (20.0, 25.0, 40.0)


def _sim():
    from eofnn.interop.oopao import OopaoLoop

    return OopaoLoop(40, 8.0, sensor="shack_hartmann", photon_noise=True, magnitude=8.0, rcond=0.075, layers=LAYERS)


def recorded() -> Telemetry:
    from eofnn.studies.twin_transfer import record_loop

    if not (RUNS / "rec.npz").exists():
        sim = _sim()
        t = record_loop(sim, 4000, 0)
        np.save(RUNS / "im.npy", sim.interaction_matrix)
        np.save(RUNS / "r.npy", sim.reconstructor)
        np.savez(RUNS / "rec.npz", y=t.y.numpy(), wfs=t.wfs.numpy(), positions_m=t.positions_m.numpy(),
                 delay_frames=t.delay_frames, frame_rate_hz=t.frame_rate_hz)
    d = np.load(RUNS / "rec.npz")
    return Telemetry(y=torch.from_numpy(d["y"]), wfs=torch.from_numpy(d["wfs"]), delay_frames=int(d["delay_frames"]),
                     frame_rate_hz=float(d["frame_rate_hz"]), positions_m=torch.from_numpy(d["positions_m"]))


def optical_gain() -> dict:
    from eofnn.interop.oopao import measure_sensor_gain

    path = RUNS / "optical_gain.json"
    if not path.exists():
        sim = _sim()
        path.write_text(json.dumps({("noise_free" if nf else "noisy"): measure_sensor_gain(
            sim, 0.25, 1500, 500, dither_nm=10.0, noise_free=nf) for nf in (False, True)}))
    return json.loads(path.read_text())


def refits(telemetry: Telemetry) -> tuple[dict, list[dict]]:
    """The twin's r0 as a user gets it (the default outer scales, ``twin.OUTER_SCALES_M``) and r0 against each of
    OUTER_SCALES_M's references alone (one identification with all of them: each outer scale's reference streams are
    the same whichever others are computed beside it)."""
    im, rec = np.load(RUNS / "im.npy"), np.load(RUNS / "r.npy")
    default = tuple(twin.OUTER_SCALES_M)
    seen, original = {}, twin.seeing_and_noise

    def capture(pol, references, positions, pitch, **kw):
        seen.setdefault("args", (pol, references, positions, pitch))
        return original(pol, references, positions, pitch, **kw)

    twin.OUTER_SCALES_M = seeing.OUTER_SCALES_M = tuple(sorted({*default, *OUTER_SCALES_M}))
    twin.seeing_and_noise = capture
    try:
        found = twin.identify_twin(telemetry, interaction_matrix=im, reconstructor=rec, command_unit="peak")
    finally:
        twin.seeing_and_noise, twin.OUTER_SCALES_M = original, default
    pol, references, positions, pitch = seen["args"]
    _, fit = original(pol, {l0: references[l0] for l0 in default}, positions, pitch)
    user = {"r0_m": fit["r0_m"], "outer_scale_m": fit["outer_scale_m"], "outer_scales_m": default,
            "dm_gain": found.value("dm_gain")}
    gains = {"none": 1.0, "probes (truth)": optical_gain()["noise_free"]["mean"], "identified": user["dm_gain"]}
    rows = []
    for label, gain in gains.items():
        for l0 in OUTER_SCALES_M:
            _, fit = original(pol / gain, {l0: references[l0]}, positions, pitch)
            rows.append({"optical_gain": label, "gain": gain, "outer_scale_m": l0, "r0_m": fit["r0_m"],
                         "r0_rel_error": fit["r0_m"] / R0_M - 1, "misfit": fit["misfit"][str(l0)]})
    return user, rows


def main() -> None:
    RUNS.mkdir(parents=True, exist_ok=True)
    OUT.mkdir(parents=True, exist_ok=True)
    telemetry = recorded()
    gain = optical_gain()
    user, rows = refits(telemetry)
    summary = {"command": "OMP_NUM_THREADS=1 .venv/bin/python experiments/interop/twin_r0_40.py",
               "truth": {"r0_m": R0_M, "outer_scale_m": 25.0, "dm_gain": 1.0}, "twin": user,
               "optical_gain_probes": gain, "refits": rows}
    (OUT / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
