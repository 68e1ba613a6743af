"""Why the EOF loses to the integrator in OOPAO's pyramid loop at I = 10 (``examples/oopao_loop.py --small --sensor
pyramid --photon-noise --magnitude 10 --frames 1000``): the study's recording and identification (seed 0, gain
0.25, 10 nm dither, 1000 frames, 300 settling), then the closed-loop EOF (4 taps) fitted at each ridge alpha given
(relative, as the study's ``auto`` path; ``auto``: its choice on 200 validation frames), with and without the
study's refit round, each run in OOPAO's loop on the study's scored realisation (seed 2, 500 frames, 300 settling:
the median residual of the last 200), beside the integrator at the recording's gain on the same realisation.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python experiments/pyramid/photon_noise_eof.py \
        --alphas auto 0.1 1 10 --out experiments/pyramid/photon_noise_eof/summary.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import time

import numpy as np

from eofnn.data.history import HistorySpec
from eofnn.interop.loop import FilterControl, IntegratorControl, run_closed_loop, runtime_filter
from eofnn.interop.oopao import OopaoLoop
from eofnn.studies.study import ALPHA_PATH
from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry
from eofnn.training.identify import identify_plant
from eofnn.training.task import OptimizationConfig


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--alphas", nargs="+", default=["auto", "0.1", "1", "10"])
    p.add_argument("--magnitude", type=float, default=10.0)
    p.add_argument("--frames", type=int, default=1000)
    p.add_argument("--loop-frames", type=int, default=500)
    p.add_argument("--dm-gain-fed", type=float, default=None, help="simulator knowledge: replaces the identified gain")
    p.add_argument("--noise-only", action="store_true",
                   help="also run each controller in the same loop without turbulence (OPD zero: what the detector's "
                        "noise alone leaves through the loop)")
    p.add_argument("--out", default=None)
    a = p.parse_args()
    t0 = time.time()
    sim = OopaoLoop(10, 2.0, sensor="pyramid", photon_noise=True, magnitude=a.magnitude, dm_gain=2.0,
                    wind_speed_mps=20.0)
    recorded = run_closed_loop(sim, IntegratorControl(0.25, 10.0, seed=100), a.frames, 0)
    telemetry = recorded.telemetry(start=300)
    plant = identify_plant(telemetry)
    if a.dm_gain_fed is not None:
        plant.dm_gain = a.dm_gain_fed
    spec = HistorySpec("closed_loop", 4, sim.delay_frames)
    data = TelemetryDataConfig(val_frames=a.frames // 5, seed=0)

    def loop(control) -> float:
        return run_closed_loop(sim, control, a.loop_frames, 2).metrics(300).summary()["median_rms_nm"]

    flat = None
    if a.noise_only:
        res = sim.tel.resolution
        flat = OopaoLoop(10, 2.0, sensor="pyramid", photon_noise=True, magnitude=a.magnitude, dm_gain=2.0,
                         wind_speed_mps=20.0, opd_source=lambda seed: itertools.repeat(np.zeros((res, res))))

    def noise_only(control) -> float | None:
        if flat is None:
            return None
        record = run_closed_loop(flat, control, a.loop_frames, 2, divergence_factor=np.inf)
        return record.metrics(300).summary()["median_rms_nm"]

    results = {"dm_gain": plant.dm_gain, "integrator_0.25": loop(IntegratorControl(0.25))}
    results["integrator_0.2"] = loop(IntegratorControl(0.2))
    results["noise_only_integrator_0.25"] = noise_only(IntegratorControl(0.25))
    print(f"noise only: integrator 0.25 {results['noise_only_integrator_0.25']} nm", flush=True)
    print(f"DM gain {plant.dm_gain:.4f}; integrator 0.25: {results['integrator_0.25']:.2f} nm, 0.2: "
          f"{results['integrator_0.2']:.2f} nm ({time.time() - t0:.0f} s)", flush=True)
    for alpha in a.alphas:
        opt = OptimizationConfig(alpha="auto" if alpha == "auto" else float(alpha), alpha_path=ALPHA_PATH)
        fitted = fit_from_telemetry(telemetry, spec, plant=plant, data=data, optimization=opt)
        chosen = fitted.info.get("alpha")
        once = loop(FilterControl(runtime_filter(fitted.network, spec, fitted.predictor.dm_gain_model), 0.25, 100))
        once_noise = noise_only(FilterControl(runtime_filter(fitted.network, spec, fitted.predictor.dm_gain_model),
                                              0.25, 100))
        print(f"alpha {alpha}: fitted once, noise only {once_noise} nm", flush=True)
        recorder = FilterControl(runtime_filter(fitted.network, spec, fitted.predictor.dm_gain_model), 0.25, 100,
                                 10.0, seed=200)
        again = run_closed_loop(sim, recorder, a.frames, 10)
        if again.diverged_frame is None:
            refit = fit_from_telemetry(again.telemetry(start=300), spec, plant=plant, data=data, optimization=opt)
            twice = loop(FilterControl(runtime_filter(refit.network, spec, refit.predictor.dm_gain_model), 0.25, 100))
            refit_alpha = refit.info.get("alpha")
        else:
            twice, refit_alpha = f"its recording diverged at frame {again.diverged_frame}", None
        results[f"alpha {alpha}"] = {"chosen": chosen, "refit_chosen": refit_alpha,
                                     "eof_no_refit_nm": once, "eof_refit_nm": twice,
                                     "noise_only_eof_no_refit_nm": once_noise}
        print(f"alpha {alpha} (chosen {chosen}, refit {refit_alpha}): EOF {once} nm (None where it diverged), after the "
              f"refit {twice} ({time.time() - t0:.0f} s)", flush=True)
    if a.out:
        with open(a.out, "w") as fh:
            json.dump({"settings": vars(a), **results}, fh, indent=1, default=str)


if __name__ == "__main__":
    main()
