"""Experiment: the wind changes at t = 5 s; static, RLS and blend open-loop EOF filters compared.

    PYTHONPATH=. .venv/bin/python experiments/adaptive_wind_turn.py --change direction|speed [--out DIR]

The change is a splice of two turbulence streams in :class:`SplicedTurbulence`, which serves frames like a
:class:`~eofnn.sim.turbulence.Turbulence`:

- ``direction``: wind along +x, then along +y (same seed, so the same screen statistics; a different screen, so
  a 0.1 s crossfade joins them);
- ``speed``: 10 m/s, then 20 m/s along +x on the same screen, continuous at the splice (the fast stream is
  entered at the frame where it has moved as far as the slow one).

Reference: an open-loop EOF retrained for the new wind. Re-convergence time: seconds after the change until the
200-frame running median of the residual RMS (its window entirely after the change) is within 10% of the
reference's median and stays there for 1 s.
Writes ``wind_<change>.json`` and ``wind_<change>.png`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from eofnn.control.adaptive import BlendController, RLSController  # noqa: E402
from eofnn.data.history import HistorySpec  # noqa: E402
from eofnn.data.stream import DataConfig  # noqa: E402
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Plant, run_loop  # noqa: E402
from eofnn.sim.scenario import Scenario  # noqa: E402
from eofnn.training.fit import fit_predictor  # noqa: E402


class SplicedTurbulence:
    """Frames of ``before`` up to ``switch_frame``, then frames ``n - after_offset`` of ``after``.

    With ``crossfade_frames``, the first frames after the switch are ``(1 - a) before + a after`` with ``a``
    rising linearly to 1 (two independent screens would otherwise jump at the switch).
    """

    def __init__(self, before, after, switch_frame: int, after_offset: int = 0, crossfade_frames: int = 0) -> None:
        self.before, self.after, self.switch_frame, self.after_offset = before, after, switch_frame, after_offset
        self.crossfade_frames = crossfade_frames
        self.grid, self.n_realisations = before.grid, before.n_realisations

    def frames(self, start: int, stop: int) -> torch.Tensor:
        cut = min(max(self.switch_frame, start), stop)
        parts = [self.before.frames(start, cut)] if cut > start else []
        if stop > cut:
            after = self.after.frames(cut - self.after_offset, stop - self.after_offset)
            fade_stop = min(stop, self.switch_frame + self.crossfade_frames)
            if fade_stop > cut:
                n = torch.arange(cut, fade_stop, dtype=torch.float64)
                a = ((n - self.switch_frame + 1) / (self.crossfade_frames + 1)).view(1, -1, 1)
                k = fade_stop - cut
                after[:, :k] = (1 - a) * self.before.frames(cut, fade_stop) + a * after[:, :k]
            parts.append(after)
        return torch.cat(parts, 1)

    def chunks(self, n_frames: int, chunk: int = 1024, start: int = 0):
        for first in range(start, start + n_frames, chunk):
            yield first, self.frames(first, min(first + chunk, start + n_frames))


def reconvergence_frames(rms: torch.Tensor, switch: int, level: float, window: int = 200,
                         hold: int = 1000) -> int | None:
    """Frames after ``switch`` until the running median (window entirely after the switch) is within 10% of
    ``level`` and stays there for ``hold`` frames."""
    smooth = running_median(rms[switch:], window)
    ok = smooth <= 1.1 * level
    for i in range(window, len(ok) - hold + 1):
        if bool(ok[i: i + hold].all()):
            return i
    return None


def running_median(x: torch.Tensor, window: int) -> torch.Tensor:
    """Median over the last ``window`` frames (shorter at the start)."""
    padded = torch.cat([x[:1].expand(window - 1), x])
    return padded.unfold(0, window, 1).median(-1).values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--change", choices=("direction", "speed"), default="direction")
    parser.add_argument("--out", default="outputs/wind_change")
    parser.add_argument("--n-across", type=int, default=10)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rate, switch_s = 1000.0, 5.0
    n_frames, switch = int(args.seconds * rate), int(switch_s * rate)
    grid = ActuatorGrid(2.0, args.n_across)

    def scenario(speed_mps: float, direction_deg: float) -> Scenario:
        atmosphere = Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=20.0,
                                layers=(Layer(1.0, speed_mps, direction_deg),))
        return Scenario(grid, atmosphere, rate, Plant(delay_frames=2, wfs_noise_nm=1.0))

    if args.change == "direction":
        along_x, along_y, offset, label = scenario(10.0, 0.0), scenario(10.0, 90.0), 0, "wind turns by 90°"
        crossfade = 100
    else:
        # 20 m/s frame n - switch / 2 has moved as far as 10 m/s frame n at the switch: a continuous splice.
        along_x, along_y, offset, label = scenario(10.0, 0.0), scenario(20.0, 0.0), switch // 2, "wind 10 -> 20 m/s"
        crossfade = 0
    spec = HistorySpec("open_loop", 6, 2)
    data = DataConfig(frames=5000, val_frames=500, sequence_frames=2500)
    static = fit_predictor(along_x, spec.kind, spec.history_length, data=data).predictor
    retrained = fit_predictor(along_y, spec.kind, spec.history_length, data=data).predictor
    weights = static.network.weight.detach()
    turbulence = SplicedTurbulence(along_x.turbulence(9), along_y.turbulence(9), switch, offset, crossfade)
    controllers = {
        "static (fitted before the change)": static.controller(),
        "RLS, forgetting 0.999": RLSController(spec, weights, forgetting=0.999),
        "blend, every 250, window 1000, gain 0.5": BlendController(spec, weights, every_frames=250,
                                                                    window_frames=1000, gain=0.5),
    }
    reference = run_loop(along_y.turbulence(9), along_y.plant, retrained.controller(), n_frames - switch, record=())
    level = float(reference.residual_rms_nm[0, 500:].median())
    summary = {"change": args.change, "retrained_median_rms_nm": level, "switch_s": switch_s, "n_actuators": grid.n_actuators,
               "history": spec.to_dict(), "controllers": {}}
    fig, ax = plt.subplots(figsize=(9, 4.5))
    time_s = torch.arange(n_frames) / rate
    for name, controller in controllers.items():
        result = run_loop(turbulence, along_x.plant, controller, n_frames, record=())
        rms = result.residual_rms_nm[0]
        smooth = running_median(rms, 200)
        frames = reconvergence_frames(rms, switch, level)
        entry = {
            "diverged": result.diverged,
            "fallback_frame": getattr(controller, "fallback_frame", None),
            "median_rms_before_nm": float(rms[switch - 2000: switch].median()),
            "median_rms_after_nm": float(rms[switch + 2000:].median()) if len(rms) > switch + 2000 else None,
            "reconvergence_s": frames / rate if frames is not None else None,
        }
        summary["controllers"][name] = entry
        print(f"{name:42s} " + " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in entry.items()))
        ax.semilogy(time_s[: len(smooth)], smooth, label=name)
    ax.axhline(level, color="black", linestyle=":", label="retrained for the new wind")
    ax.axvline(switch_s, color="grey", linewidth=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("residual RMS, 200-frame running median (nm)")
    ax.set_title(f"{label} at t = {switch_s:g} s ({grid.n_actuators} actuators, 1 nm WFS noise)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / f"wind_{args.change}.png", dpi=110)
    print(f"retrained for the new wind: {level:.4g} nm")
    (out / f"wind_{args.change}.json").write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
