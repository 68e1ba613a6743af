"""Experiment: the DM gain drifts from 1 to 1.5 (or more) over 10 s; static and adapting closed-loop EOF compared.

    PYTHONPATH=. .venv/bin/python experiments/adaptive_dm_gain_drift.py [--end-gain 1.5] [--out DIR]

The drift is applied by :class:`DriftingDMGain`, a wrapper that multiplies the commands of the controller it
wraps by ``g(n)`` on their way to a nominal DM: the controller (which believes the gain is 1) sees exactly the
loop of a DM whose gain is ``g(n)``. The analytic stability of the static filter (:mod:`eofnn.analysis.stability`)
predicts the gain, hence the time, at which it must diverge; the adapting filters' final weights are analysed at
the final gain. Writes ``dm_gain_drift_<end gain>.json`` and ``.png`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from eofnn.analysis.stability import LoopSetup, analyse, analyse_filter  # noqa: E402
from eofnn.control.adaptive import BlendController, RLSController  # noqa: E402
from eofnn.data.history import HistorySpec  # noqa: E402
from eofnn.data.stream import DataConfig  # noqa: E402
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Plant, run_loop  # noqa: E402
from eofnn.sim.scenario import Scenario  # noqa: E402
from eofnn.training.fit import fit_predictor  # noqa: E402


class DriftingDMGain:
    """Scales another controller's commands by a DM gain ramping linearly from ``start`` to ``end`` over
    ``ramp_frames`` frames (then held), so that a nominal plant behaves as a drifting DM."""

    def __init__(self, controller, start: float, end: float, ramp_frames: int) -> None:
        self.controller, self.start, self.end, self.ramp_frames = controller, start, end, ramp_frames

    def gain(self, frame: int) -> float:
        return self.start + (self.end - self.start) * min(frame / self.ramp_frames, 1.0)

    def reset(self, batch: int, n_actuators: int, delay_frames: int, dtype: torch.dtype) -> None:
        self.controller.reset(batch, n_actuators, delay_frames, dtype)

    def step(self, inp):
        return self.gain(inp.frame) * self.controller.step(inp)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="outputs/dm_gain_drift")
    parser.add_argument("--n-across", type=int, default=10)
    parser.add_argument("--end-gain", type=float, default=1.5)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rate, ramp_s, hold_s, end_gain = 1000.0, 10.0, 2.0, args.end_gain
    ramp, n_frames = int(ramp_s * rate), int((ramp_s + hold_s) * rate)
    atmosphere = Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=(Layer(1.0, 10.0, 0.0),))
    scenario = Scenario(ActuatorGrid(2.0, args.n_across), atmosphere, rate, Plant(delay_frames=2, wfs_noise_nm=5.0))
    spec = HistorySpec("closed_loop", 5, 2)
    data = DataConfig(frames=5000, val_frames=500, sequence_frames=2500, dither_nm=10.0)
    static = fit_predictor(scenario, spec.kind, spec.history_length, data=data).predictor
    weights = static.network.weight.detach()
    analysis = analyse_filter(static.network, spec, LoopSetup.from_plant(scenario.plant))
    upper = analysis.gain_margin[1]
    predicted_s = (upper - 1.0) / (end_gain - 1.0) * ramp_s if upper < end_gain else None
    summary = {"static_dm_gain_interval": list(analysis.gain_margin), "predicted_static_divergence_s": predicted_s,
               "end_gain": end_gain, "ramp_s": ramp_s, "n_actuators": scenario.grid.n_actuators, "controllers": {}}
    print(f"static filter: stable for DM gain in {analysis.gain_margin}; predicted divergence at "
          f"{predicted_s if predicted_s is None else f'{predicted_s:.2f} s'}")
    controllers = {
        "static closed-loop EOF": static.controller(),
        "RLS, forgetting 0.999": RLSController(spec, weights, forgetting=0.999),
        "RLS, forgetting 0.999, 2 nm dither": RLSController(spec, weights, forgetting=0.999, dither_nm=2.0),
        "blend, every 250, window 1000, gain 0.5, 2 nm dither": BlendController(
            spec, weights, every_frames=250, window_frames=1000, gain=0.5, dither_nm=2.0),
    }
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for name, controller in controllers.items():
        drifting = DriftingDMGain(controller, 1.0, end_gain, ramp)
        result = run_loop(scenario.turbulence(9), scenario.plant, drifting, n_frames, record=())
        rms = result.residual_rms_nm[0]
        entry = {"diverged": result.diverged,
                 "diverged_s": None if result.diverged_frame is None else result.diverged_frame / rate,
                 "fallback_s": None, "median_rms_first_2s_nm": float(rms[500:2000].median()),
                 "median_rms_last_2s_nm": float(rms[-2000:].median()) if len(rms) == n_frames else None}
        if isinstance(controller, (RLSController, BlendController)):
            frame = controller.fallback_frame
            entry["fallback_s"] = None if frame is None else frame / rate
            final = analyse(controller.weights[0], "closed_loop", spec.history_length,
                            LoopSetup(delay_frames=2, dm_gain=end_gain))
            entry["final_filter_at_end_gain"] = {"stable": final.stable,
                                                 "max_root_modulus": float(final.max_root_modulus.max()),
                                                 "dm_gain_interval": list(final.gain_margin)}
        summary["controllers"][name] = entry
        print(f"{name:52s} {entry}")
        ax.semilogy(torch.arange(len(rms)) / rate, rms, label=name, linewidth=0.8)
    if predicted_s is not None:
        ax.axvline(predicted_s, color="grey", linestyle=":", label="static filter leaves its analytic margin")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("residual RMS (nm)")
    ax.set_title(f"DM gain 1 -> {end_gain:g} over {ramp_s:g} s ({scenario.grid.n_actuators} actuators, 5 nm WFS noise)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / f"dm_gain_drift_{end_gain:g}.png", dpi=110)
    (out / f"dm_gain_drift_{end_gain:g}.json").write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
