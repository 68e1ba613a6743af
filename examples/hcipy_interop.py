"""eofnn's closed-loop EOF inside an HCIPy loop: infinite frozen-flow layer, Gaussian-influence Fried DM applying 2x
its command, a phase-projection sensor with white noise, 1 kHz, two-frame delay.

The chain of ``examples/oopao_loop.py`` (:func:`eofnn.studies.study.run_study`): record telemetry in the HCIPy
loop with an integrator and 10 nm of dither, identify the plant, fit a closed-loop EOF from the telemetry alone
(refit once on its own telemetry), replay it on a held-out realisation, and run the exported runtime filter in
the HCIPy loop against the best-gain integrator (residual OPD, median RMS over the pupil).

    python examples/hcipy_interop.py --small                       # 10 x 10 on 2 m (CI size)
    python examples/hcipy_interop.py --n-subapertures 40 --diameter 8 --out experiments/runs/interop/hcipy
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace

from eofnn.interop.hcipy import HcipyLoop
from eofnn.studies.report import example_parser, parse_example, split_text, write_results
from eofnn.studies.study import StudyConfig, run_study


def main(argv: list[str] | None = None) -> dict:
    parser = example_parser(__doc__.splitlines()[0])
    parser.add_argument("--noise", type=float, default=2.0, help="white measurement noise, nm per actuator")
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_example(parser, argv)
    started = time.time()
    sim = HcipyLoop(args.n_subapertures, args.diameter, dm_gain=args.dm_gain, wind_speed_mps=args.wind,
                    wfs_noise_nm=args.noise)
    config = replace(StudyConfig.from_frames(args.frames, gains=(0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45)),
                     scored_realisations=args.realisations)
    run = run_study(sim, config, dm_gain_true=args.dm_gain).summary()
    run["seconds"] = round(time.time() - started, 1)
    print(f"DM gain identified {run['identified']['dm_gain']:.4f} (true {args.dm_gain}); replay: EOF "
          f"{run['replay']['predictor_median_rms_nm']:.2f} nm vs integrator "
          f"{run['replay']['integrator_median_rms_nm']:.2f} nm; in HCIPy's loop: EOF {run['eof']['median_rms_nm']:.2f} "
          f"nm vs best-gain integrator {run['integrator']['median_rms_nm']:.2f} nm (gain "
          f"{run['integrator']['best_gain']}); split {split_text(run.get('split'))} ({run['seconds']} s)")
    metrics = {"runs": {"phase_projection": run}}
    if args.out:
        write_results(args.out, "HCIPy", metrics, " ".join(["python examples/hcipy_interop.py", *argv]))
    return metrics


if __name__ == "__main__":
    main()
