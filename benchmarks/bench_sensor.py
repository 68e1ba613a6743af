"""Benchmark: a closed loop through the Shack-Hartmann against the same loop through today's zonal sensing, timed in
the same run.

    PYTHONPATH=. .venv/bin/python -m benchmarks.bench_sensor                      # 40 across, 1000 frames
    PYTHONPATH=. .venv/bin/python -m benchmarks.bench_sensor --n-across 10 --frames 200 --repeat 1   # smoke size

Both run an integrator (gain 0.5) on configs/realistic.yaml's sky (two layers of exact frozen flow, 5.1 m/s along x
and 10 m/s along y) for ``--frames`` frames, one realisation, set-up included (a fresh turbulence each time):

- ``sensor/first``: the Shack-Hartmann, the fine-grid phase synthesised (16 points per actuator) and its chunks
  computed: what the first controller on a test stream pays;
- ``sensor/cached``: the Shack-Hartmann again on the same stream, its chunks cached (every later controller and every
  gain of a scan);
- baseline: the zonal sensing (the subaperture mean at each actuator).

The rows are information (no goal): the ratio ``zonal / Shack-Hartmann`` says how many times slower the real
sensor's loop is. ``results_sensor.json`` holds the last run.
"""

from __future__ import annotations

import torch

from benchmarks.common import Row, sized_main, time_interleaved
from eofnn.control.baselines import Integrator
from eofnn.sim.loop import sensing
from eofnn.sim.loop.runner import run_loop
from eofnn.sim.scenario import Scenario


def _scenario(n_across: int, frames: int, shack_hartmann: bool) -> Scenario:
    config = {"grid": {"diameter_m": 8.0, "n_across": n_across},
              "atmosphere": {"r0_m": 0.083, "r0_wavelength_m": 6.58e-7, "outer_scale_m": 20.0, "screen_frames": frames,
                             "layers": [{"cn2_fraction": 0.5, "wind_speed_mps": 5.1, "wind_direction_deg": 0.0},
                                        {"cn2_fraction": 0.5, "wind_speed_mps": 10.0, "wind_direction_deg": 90.0}]},
              "plant": {"delay_frames": 2}}
    if shack_hartmann:
        config["sensor"] = {"kind": "shack_hartmann", "detector": {"magnitude": 8.0}}
    return Scenario.from_dict(config)


def bench_sensor(n_across: int = 40, frames: int = 1000, repeat: int = 2) -> list[Row]:
    zonal, sh = _scenario(n_across, frames, False), _scenario(n_across, frames, True)

    def run(scenario: Scenario, fresh: bool):
        if fresh:
            sensing.clear_cache()
        return run_loop(scenario.turbulence(1, "bench"), scenario.plant, Integrator(0.5), frames, record=())

    run(sh, True)  # builds the sensor's operators (kept for the study, as in compare)
    calls = {"zonal": (lambda: run(zonal, False), 1), "first": (lambda: run(sh, True), 1),
             "cached": (lambda: run(sh, False), 1)}
    timings = time_interleaved(calls, repeat=repeat, warmup=0)
    info = {"n_across": n_across, "n_actuators": sh.grid.n_actuators, "frames": frames,
            "fine_points": sh.turbulence(1, "bench").n_fine, "threads": torch.get_num_threads()}
    return [Row("sensor", f"sensor/{which}/{n_across}x{frames}", "s/run", timings[which], timings["zonal"],
                "zonal sensing, same loop and sky", info=info) for which in ("first", "cached")]


def main(argv: list[str] | None = None) -> list[dict]:
    return sized_main(argv, __doc__, 1000, lambda frames, n_across, repeat: bench_sensor(n_across, frames, repeat),
                      lambda row: f"{row['name']}: Shack-Hartmann {row['eofnn_s']['min']:.2f} s, zonal "
                                  f"{row['baseline_s']['min']:.2f} s, ratio {row['ratio']:.3f}")


if __name__ == "__main__":
    main()
