"""Diagnostic (simulator knowledge): the study of ``examples/oopao_loop.py --small --sensor pyramid --photon-noise
--magnitude 10 --frames 1000`` with the identified DM gain replaced by a given value (e.g. 2 x the optical gain
measured noise-free on the recorded loop's residuals by ``photon_noise.py``), to see whether the EOF's loss to the
integrator in OOPAO's loop comes from the identified gain.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python experiments/pyramid/photon_noise_gain.py --dm-gain-fed 1.766
    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python experiments/pyramid/photon_noise_gain.py   # identified (baseline)
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import eofnn.studies.study as study_module
from eofnn.interop.oopao import OopaoLoop
from eofnn.studies.study import StudyConfig, run_study


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dm-gain-fed", type=float, default=None, help="DM gain given to the fit (default: identified)")
    p.add_argument("--magnitude", type=float, default=10.0)
    p.add_argument("--frames", type=int, default=1000)
    p.add_argument("--out", default=None)
    a = p.parse_args()
    identify = study_module.identify_plant

    def fed(*args, **kwargs):
        plant = identify(*args, **kwargs)
        print(f"identified DM gain {plant.dm_gain:.4f}" + ("" if a.dm_gain_fed is None else
                                                          f"; replaced by {a.dm_gain_fed:.4f}"), flush=True)
        if a.dm_gain_fed is not None:
            plant.dm_gain = a.dm_gain_fed
        return plant

    study_module.identify_plant = fed
    sim = OopaoLoop(10, 2.0, sensor="pyramid", photon_noise=True, magnitude=a.magnitude, dm_gain=2.0,
                    wind_speed_mps=20.0)
    config = replace(StudyConfig.from_frames(a.frames, gains=(0.15, 0.2, 0.25, 0.3, 0.35, 0.4)), scored_realisations=1)
    t0 = time.time()
    r = run_study(sim, config, dm_gain_true=2.0).summary()
    print(f"fed {a.dm_gain_fed}: replay EOF {r['replay']['predictor_median_rms_nm']:.2f} vs integrator "
          f"{r['replay']['integrator_median_rms_nm']:.2f} nm (noise {r['replay']['noise_nm']:.1f}); OOPAO's loop: EOF "
          f"{r['eof']['median_rms_nm']:.2f} vs best integrator {r['integrator']['median_rms_nm']:.2f} nm (gain "
          f"{r['integrator']['best_gain']}); scan {r['integrator']['scan']} ({time.time() - t0:.0f} s)")
    if a.out:
        with open(a.out, "w") as fh:
            json.dump({"dm_gain_fed": a.dm_gain_fed, **r}, fh, indent=1, default=str)


if __name__ == "__main__":
    main()
