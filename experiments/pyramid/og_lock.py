"""Why og_robustness.yaml's best-gain integrator loses lock: one integrator run of its scenario, varied.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python experiments/pyramid/og_lock.py VARIANT [GAIN [FRAMES]]

VARIANT: ``change`` (the experiment's scenario: r0 0.15 -> 0.105 m at 1.1 s), ``change_spp3`` (that at 3 pupil
samples per pixel instead of 2), ``strong`` (no change, r0 = 0.105 m from the start), ``strong_spp3`` /
``strong_spp4`` (that at 3 or 4 samples per pixel), ``compensated`` (the change, optical gains compensated).
Integrator gain GAIN (0.65: the uncompensated scan's choice), FRAMES frames (2000), test stream of seed 1,
uncompensated unless asked. Prints the median residual over the pupil per 100 frames and per 10 frames over
1400-1600 (with a change: before it and after it, as og_robustness_summary.py splits them), and the optical gains
(KL modes 1-8 and 21-40, and the least of 40) about the residual at 10 frames spread over the run. The same lines
go into ``og_lock/summary.json`` under the variant's name (``--out FILE`` elsewhere; other variants kept).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch
import yaml

from eofnn.control.baselines import Integrator
from eofnn.sim.loop.runner import run_loop
from eofnn.sim.scenario import Scenario
from eofnn.sim.sensing.optical_gains import OpticalGainProbe, kl_modes, optical_gains

CONFIG = Path(__file__).with_name("og_robustness.yaml")


def scenario(variant: str) -> Scenario:
    cfg = yaml.safe_load(CONFIG.read_text())["scenario"]
    if variant.startswith("strong"):
        cfg["atmosphere"].pop("changes")
        cfg["atmosphere"]["r0_m"] = 0.105  # 0.15 x 1.81^(-3/5): the sky after the change
        if variant != "strong":
            cfg["sensor"]["samples_per_pixel"] = int(variant[-1])
    elif variant == "compensated":
        cfg["sensor"]["optical_gain_compensation"] = True
    elif variant == "change_spp3":
        cfg["sensor"]["samples_per_pixel"] = 3
    elif variant != "change":
        raise SystemExit(f"variant {variant!r} is invalid: allowed are change, change_spp3, strong, strong_spp3, "
                         "strong_spp4, compensated")
    return Scenario.from_dict(cfg)


def main(argv: list[str]) -> None:
    out = Path(__file__).with_name("og_lock") / "summary.json"
    if "--out" in argv:
        i = argv.index("--out")
        if i + 1 >= len(argv):
            raise SystemExit("--out needs a file name")
        out = Path(argv[i + 1])
        argv = argv[:i] + argv[i + 2:]
    if not argv:
        raise SystemExit("give a VARIANT: change, change_spp3, strong, strong_spp3, strong_spp4 or compensated")
    lines: list[str] = []

    def say(text: str, *values) -> None:  # print the line and keep it for the summary
        line = " ".join([text, *map(str, values)])
        lines.append(line)
        sys.stdout.write(line + "\n")

    variant = argv[0]
    gain = float(argv[1]) if len(argv) > 1 else 0.65
    frames = int(argv[2]) if len(argv) > 2 else 2000
    sc = scenario(variant)
    turbulence = sc.turbulence(1, "test")
    sensor = turbulence.operators.sensor
    probe = OpticalGainProbe(sensor, 0, frames, n_modes=40, n_frames=10)
    result = run_loop(turbulence, sc.plant, Integrator(gain), frames, noise_seed=1, record=(), on_chunk=probe,
                      divergence_factor=50.0)
    r = result.pupil_residual_rms_nm[0]
    say(f"{variant}, gain {gain}: diverged at {result.diverged_frame}")
    say("median per 100 frames (nm):", [round(float(r[i:i + 100].median())) for i in range(0, len(r), 100)])
    if sc.atmosphere.changes:  # og_robustness_summary.py's split: settled frames to the change, 50 ms after its ramp
        start = round(sc.atmosphere.changes[0].at_s * 1000.0)
        after = round((sc.atmosphere.changes[0].at_s + sc.atmosphere.changes[0].ramp_s + 0.05) * 1000.0)
        say(f"median before the change {float(r[200:start].median()):.1f} nm, after {float(r[after:].median()):.1f} "
            f"nm, p95 {float(r[200:].quantile(0.95)):.1f} nm")
    say("median per 10 frames over 1400-1600 (nm):",
        [round(float(r[i:i + 10].median())) for i in range(1400, min(1600, len(r)), 10)])
    shapes = sensor.dm_surface(torch.as_tensor(kl_modes(sensor.grid, 40).T))
    for frame, residual in zip(probe.frames, probe.residuals, strict=False):
        g = optical_gains(sensor, shapes, residual)[0]
        say(f"frame {frame}: optical gains low {float(g[:8].mean()):.3f}, high {float(g[20:].mean()):.3f}, "
            f"least {float(g.min()):.3f}")
    record = json.loads(out.read_text()) if out.exists() else {}
    record[f"{variant} gain {gain} frames {frames}" if (gain, frames) != (0.65, 2000) else variant] = lines
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(dict(sorted(record.items())), indent=1) + "\n")
    tmp.replace(out)


if __name__ == "__main__":
    main(sys.argv[1:])
