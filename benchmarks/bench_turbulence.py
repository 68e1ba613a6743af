"""Benchmark 1: turbulence frames per second on the actuator grid, eofnn against a plain HCIPy loop."""

from __future__ import annotations

import dataclasses

from benchmarks.baselines import HcipyTurbulence
from benchmarks.common import Row, Timing, time_interleaved, time_once
from eofnn.sim.atmosphere.turbulence import Turbulence
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.scenario import Scenario


def scenario_with_grid(scenario: Scenario, n_across: int, diameter_m: float | None = None) -> Scenario:
    """``scenario`` on another actuator grid (same atmosphere, frame rate and plant)."""
    grid = ActuatorGrid(diameter_m or scenario.grid.diameter_m, n_across, scenario.grid.obstruction)
    return dataclasses.replace(scenario, grid=grid)


def bench_turbulence(scenario: Scenario, n_across: tuple[int, ...] = (40, 80), chunk_frames: int = 1024,
                     chunks_per_repeat: int = 10, hcipy_frames: int = 500, repeat: int = 5, setup_repeat: int = 3,
                     seed: int = 0) -> list[Row]:
    """Frames per second of :class:`eofnn.sim.Turbulence` and of the HCIPy loop, and their set-up costs.

    Per grid size two rows:

    - ``frame/<n>``: steady-state seconds per frame. eofnn streams consecutive ranges
      ``frames(k * chunk, (k + 1) * chunk)`` of ``chunk_frames`` (``run_loop``'s chunk), ``chunks_per_repeat`` per
      timing (after one untimed timing): 10 x 1024 frames extend the strip by about one 256-column block at 40
      across and two at 80, so strip growth is included, amortised as in a long run. HCIPy evolves its layer frame
      by frame.
    - ``setup/<n>``: seconds from nothing to the first frame (eofnn: ``Turbulence(...)`` plus ``frames(0, 1)``;
      HCIPy: ``InfiniteAtmosphericLayer(...)`` plus the first frame). Paid once per realisation.
    """
    rows = []
    for n in n_across:
        rows += _rows_for_grid(scenario_with_grid(scenario, n), chunk_frames, chunks_per_repeat, hcipy_frames, repeat,
                               setup_repeat, seed)
    return rows


def time_against_hcipy(turbulence: Turbulence, sc: Scenario, seed: int, chunk_frames: int, chunks_per_repeat: int,
                       hcipy_frames: int, repeat: int) -> dict[str, Timing]:
    """``{"eofnn", "hcipy"}`` s/frame: ``turbulence.frames`` streamed in consecutive ``chunk_frames`` calls
    (``chunks_per_repeat`` per timing, as ``run_loop`` asks for them) against HCIPy's layer evolved frame by frame
    on the scenario's grid, interleaved (one warm-up)."""
    hcipy_turbulence = HcipyTurbulence(sc.atmosphere, sc.grid, sc.frame_rate_hz, seed)
    state = {"next": 0}

    def chunks():
        for _ in range(chunks_per_repeat):
            first = state["next"]
            state["next"] += chunk_frames
            turbulence.frames(first, first + chunk_frames)

    return time_interleaved({"eofnn": (chunks, chunk_frames * chunks_per_repeat),
                             "hcipy": (lambda: hcipy_turbulence.frames(hcipy_frames), hcipy_frames)},
                            repeat=repeat, warmup=1)


def _rows_for_grid(sc: Scenario, chunk_frames: int, chunks_per_repeat: int, hcipy_frames: int, repeat: int,
                   setup_repeat: int, seed: int) -> list[Row]:
    n = sc.grid.n_across
    timings = time_against_hcipy(sc.turbulence(seed), sc, seed, chunk_frames, chunks_per_repeat, hcipy_frames, repeat)
    rows = [Row(
        "turbulence", f"frame/{n}", "s/frame", timings["eofnn"], timings["hcipy"],
        "HCIPy InfiniteAtmosphericLayer loop", goal_ratio=10.0, goal_label=">= 10 (10x HCIPy's rate)",
        info={"n_across": n, "n_actuators": sc.grid.n_actuators, "eofnn_frames_per_s": 1 / timings["eofnn"].min,
              "hcipy_frames_per_s": 1 / timings["hcipy"].min, "chunk_frames": chunk_frames,
              "chunks_per_repeat": chunks_per_repeat,
              "hcipy_frames": hcipy_frames},
    )]

    eofnn_setup, hcipy_setup = [], []
    for r in range(setup_repeat):
        s = seed + r + 1
        eofnn_setup.append(time_once(
            lambda s=s: Turbulence(sc.atmosphere, sc.grid, sc.frame_rate_hz, s).frames(0, 1))[0])
        hcipy_setup.append(time_once(
            lambda s=s: HcipyTurbulence(sc.atmosphere, sc.grid, sc.frame_rate_hz, s).frames(1))[0])
    rows.append(Row(
        "turbulence", f"setup/{n}", "s", Timing(eofnn_setup), Timing(hcipy_setup),
        "HCIPy InfiniteAtmosphericLayer set-up", info={"n_across": n, "n_actuators": sc.grid.n_actuators},
    ))
    return rows
