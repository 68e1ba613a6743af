"""Benchmark: plant identification from telemetry, against a closed-form fit of the same telemetry in the same run.

    .venv/bin/python -m benchmarks.bench_identify                       # 60,000 frames x 1264 actuators
    .venv/bin/python -m benchmarks.bench_identify --frames 2000 --n-across 10 --repeat 1   # smoke size

The telemetry is synthetic, with the structure identification expects (the cost does not depend on the values):
white dithered commands on a 40-across grid, a DM of gain 2 misregistered by 0.2 pitch, and smooth residuals.
Both contenders stream the same ``(frames, K)`` arrays in 1024-frame batches (never a whole history tensor):

- eofnn: :func:`eofnn.training.identify.identify_plant` (two streamed regressions per actuator: 4 then 13
  features, the lag search and the noise estimate);
- baseline: the closed-form fit of a 12-tap per-actuator closed-loop EOF on the same telemetry
  (:func:`eofnn.training.from_telemetry.fit_from_telemetry`, history length 6).

Goal: identification within 2x of the fit (``ratio = fit / identify >= 0.5``).
"""

from __future__ import annotations

import torch

from benchmarks.common import Row, sized_main, time_interleaved
from eofnn.data.history import HistorySpec
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.loop.plant import Plant, PlantModel
from eofnn.telemetry.record import Telemetry
from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry
from eofnn.training.identify import identify_plant


def synthetic_telemetry(n_frames: int, grid: ActuatorGrid, seed: int = 0) -> Telemetry:
    """``y`` = a random walk (an integrator's state) + 10 nm white dither; ``wfs = DM(y) + s``, ``s`` smooth."""
    gen = torch.Generator().manual_seed(seed)
    k = grid.n_actuators
    walk = torch.randn(n_frames, k, generator=gen, dtype=torch.float64).cumsum(0)
    y = walk + 10.0 * torch.randn(n_frames, k, generator=gen, dtype=torch.float64)
    s = torch.randn(n_frames, k, generator=gen, dtype=torch.float64).cumsum(0)
    s -= walk * 2.0  # the loop keeps the residual small: the correction follows the turbulence
    dm = PlantModel(Plant(dm_gain=2.0, misregistration_x=0.2), grid)
    wfs = s + dm.apply_dm(y) + torch.randn(n_frames, k, generator=gen, dtype=torch.float64)
    return Telemetry(y=y, wfs=wfs, delay_frames=2, positions_m=torch.as_tensor(grid.positions_m))


def bench_identify(n_frames: int = 60000, n_across: int = 40, diameter_m: float = 8.0, repeat: int = 2,
                   batch_frames: int = 1024) -> list[Row]:
    grid = ActuatorGrid(diameter_m, n_across)
    telemetry = synthetic_telemetry(n_frames, grid)
    spec = HistorySpec("closed_loop", 6, 2)
    results = {}
    calls = {
        "identify": (lambda: results.__setitem__("plant", identify_plant(telemetry, batch_frames=batch_frames)), 1),
        "fit": (lambda: fit_from_telemetry(telemetry, spec, plant={"dm_gain": 2.0},
                                           data=TelemetryDataConfig(batch_frames=batch_frames)), 1),
    }
    timings = time_interleaved(calls, repeat=repeat, warmup=0)
    plant = results["plant"]
    return [Row("identify", f"identify/{n_frames}x{grid.n_actuators}", "s/identification", timings["identify"],
                timings["fit"], "closed-form fit, 12 taps, same telemetry", goal_ratio=0.5,
                goal_label=">= 0.5 (within 2x)",
                info={"n_frames": n_frames, "n_actuators": grid.n_actuators, "batch_frames": batch_frames,
                      "data_GB": 2 * n_frames * grid.n_actuators * 8 / 1e9, "dm_gain": plant.dm_gain,
                      "misregistration_x": plant.misregistration_x, "threads": torch.get_num_threads()})]


def main(argv: list[str] | None = None) -> list[dict]:
    return sized_main(argv, __doc__, 60000,
                      lambda frames, n_across, repeat: bench_identify(frames, n_across, repeat=repeat),
                      lambda row: f"{row['name']}: identify {row['eofnn_s']['min']:.2f} s, fit "
                                  f"{row['baseline_s']['min']:.2f} s, ratio {row['ratio']:.2f} (goal {row['goal']}: "
                                  f"{'met' if row['goal_met'] else 'missed'})")


if __name__ == "__main__":
    main()
