"""Where the anti-aliasing EOF's low-frequency residual PSD came from (docs/findings.md, "The residual PSD of a loop
scored over the pupil").

Runs the best-gain integrator (gain 0.5) and the flagship's anti-aliasing EOF (5 x 5 neighbourhood, 4 taps,
data.target: dm_fit) on the flagship's test stream (seed 1), optionally on a smaller copy of its scenario, and prints
for each the temporal PSD (mean over actuators, Welch segments of 1024 frames after 300 settling frames, as
eofnn.evaluation.metrics.WelchPSD) of

- eps = R S phi + DM(y), the residual against the sensor's reconstruction (what the PSD took before),
- P F phi + DM(y), the residual against the DM's fit of the true phase (what it takes now),
- R S phi - P F phi with no loop (the command-space aliasing),

and a split of the command and of eps into piston, tip/tilt, waffle, the modes the least-squares reconstructor cuts
(I - P) and the seen modes (P), with the command's size (RMS, largest value) and the aliasing's slow part by radius.

    # the committed flagship (40 x 40, 8 m) with its checkpoint: about 1.5 minutes, single thread
    python experiments/flagship/psd_residual.py --checkpoint experiments/runs/flagship/checkpoints/ol_eof_aa__nominal.ckpt
    # a 20 x 20 copy on 4 m, the EOF trained here: about 40 s
    python experiments/flagship/psd_residual.py --n-across 20 --diameter-m 4 --realisations 1
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import yaml

from eofnn.control.baselines import Integrator
from eofnn.data.config import DataConfig
from eofnn.sim.loop.runner import run_loop
from eofnn.sim.scenario import Scenario
from eofnn.training.checkpoint import load_predictor
from eofnn.training.fit import fit_predictor

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "flagship_sh.yaml"
SETTLE, SEGMENT, RATE = 300, 1024, 1000.0


def psd(x: np.ndarray) -> np.ndarray:
    """One-sided PSD (nm²/Hz) of ``(R, frames, K)``, one Hann segment after settling, mean over rows and actuators."""
    w = np.hanning(SEGMENT)[None, :, None]
    spectrum = np.abs(np.fft.rfft(x[:, SETTLE:SETTLE + SEGMENT] * w, axis=1)) ** 2 / (RATE * (w ** 2).sum())
    spectrum[:, 1:-1] *= 2
    return spectrum.mean((0, 2))


def line(name: str, x: np.ndarray) -> str:
    p, df = psd(x), RATE / SEGMENT
    return (f"  {name}: {np.sqrt((x[:, SETTLE:] ** 2).mean()):.1f} nm RMS; PSD (nm²/Hz) at 1 Hz {p[1]:.3g}, 2 Hz "
            f"{p[2]:.3g}, 5 Hz {p[5]:.3g}, 10 Hz {p[10]:.3g}, 50 Hz {p[51]:.3g}; below 10 Hz {p[1:11].sum() * df:.3g} nm²")


def modes(grid, projector: np.ndarray) -> dict[str, np.ndarray]:
    """Orthonormal command bases of piston, tip/tilt and waffle, and the projectors on the unseen and seen modes."""
    k = grid.n_actuators
    pos, idx = np.asarray(grid.positions_m), np.asarray(grid.indices)
    tilt = np.linalg.qr(pos - pos.mean(0))[0]
    waffle = (-1.0) ** idx.sum(1)
    waffle = waffle - waffle.mean()
    bases = {"piston": np.ones((k, 1)) / np.sqrt(k), "tip/tilt": tilt,
             "waffle": (waffle / np.linalg.norm(waffle))[:, None]}
    out = {name: b @ b.T for name, b in bases.items()}
    return {**out, "unseen (I - P)": np.eye(k) - projector, "seen (P)": projector}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n-across", type=int, default=None, help="actuators across (default: the flagship's 40)")
    parser.add_argument("--diameter-m", type=float, default=None, help="telescope diameter (default: 8 m)")
    parser.add_argument("--checkpoint", default=None, help="the EOF's checkpoint (default: train one here)")
    parser.add_argument("--frames", type=int, default=1500)
    parser.add_argument("--realisations", type=int, default=2)
    args = parser.parse_args()
    config = yaml.safe_load(CONFIG.read_text())["scenario"]
    if args.n_across is not None:
        config["grid"]["n_across"] = args.n_across
    if args.diameter_m is not None:
        config["grid"]["diameter_m"] = args.diameter_m
    scenario = Scenario.from_dict(config)
    if args.checkpoint:
        eof = load_predictor(args.checkpoint, scenario).controller()
    else:
        data = DataConfig(frames=2560, val_frames=640, sequence_frames=2560, target="dm_fit", seed=0)
        network = {"class_path": "eofnn.models.linear.LinearFilter",
                   "init_args": {"structure": "neighbourhood", "radius": 2.5}}
        eof = fit_predictor(scenario, "open_loop", 4, network, data=data).controller()
    turbulence = scenario.turbulence(1, "test", args.realisations)
    products = turbulence.products(0, args.frames)
    fit, sensed = products["fit"].numpy(), products["sensed"].numpy()
    projector = turbulence.operators.projector.numpy()
    split = modes(scenario.grid, projector)
    print(f"{scenario.grid.n_across} across on {scenario.grid.diameter_m} m, {args.frames} frames, "
          f"{args.realisations} realisation(s)")
    print("no loop:")
    print(line("R S phi - P F phi (the command-space aliasing)", sensed - fit))
    slow = np.fft.rfft(sensed - fit, axis=1)
    slow[:, np.fft.rfftfreq(args.frames, 1 / RATE) >= 10] = 0
    slow_rms = np.sqrt((np.fft.irfft(slow, n=args.frames, axis=1)[:, SETTLE:] ** 2).mean((0, 1)))
    idx, n = np.asarray(scenario.grid.indices), scenario.grid.n_across
    radius = np.hypot(*(idx - (n - 1) / 2).T) / ((n - 1) / 2)
    for lo, hi in ((0, 0.4), (0.4, 0.7), (0.7, 0.85), (0.85, 2)):
        inside = (radius >= lo) & (radius < hi)
        print(f"  its part below 10 Hz at {lo}-{min(hi, 1)} of the radius ({inside.sum()} actuators): "
              f"{np.sqrt((slow_rms[inside] ** 2).mean()):.1f} nm RMS")
    for name, controller in (("integrator, gain 0.5", Integrator(0.5)), ("ol_eof_aa", eof)):
        result = run_loop(turbulence, scenario.plant, controller, args.frames, noise_seed=2, record=("y", "eps"),
                          progress=False)
        y, eps = result.telemetry.y.numpy(), result.telemetry.eps.numpy()
        settled = y[:, SETTLE:]
        unseen = y @ split["unseen (I - P)"].T
        halves = [np.sqrt((h ** 2).mean()) for h in np.array_split(unseen[:, SETTLE:], 2, axis=1)]
        print(f"{name}: pupil median {np.median(result.pupil_residual_rms_nm[:, SETTLE:].numpy()):.1f} nm; command "
              f"{np.sqrt((settled ** 2).mean()):.1f} nm RMS, largest |y| {np.abs(settled).max():.0f} nm; unseen "
              f"{100 * (unseen[:, SETTLE:] ** 2).mean() / (settled ** 2).mean():.2f}% of the command's variance, "
              f"{halves[0]:.1f} then {halves[1]:.1f} nm RMS over the two halves")
        print(line("eps = R S phi + DM(y)", eps))
        print(line("P F phi + DM(y)", fit + y))
        for part, matrix in split.items():
            print(line(f"command, {part}", y @ matrix.T))
            print(line(f"eps, {part}", eps @ matrix.T))


if __name__ == "__main__":
    main()
