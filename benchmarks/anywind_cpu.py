"""The non-lattice wind's whole-run cost against HCIPy, in CPU time (robust to other processes on a shared machine):

    .venv/bin/python -m benchmarks.anywind_cpu [--frames 8192] [--sizes 40,80]

One thread each. eofnn: build an :class:`~eofnn.sim.atmosphere.anywind.AnyWindFrozenFlow` screen (30 degrees, 10 m/s, 1 kHz,
subaperture kernel) and read every frame in 1024-frame blocks; HCIPy: the plain ``InfiniteAtmosphericLayer`` loop of
:mod:`benchmarks.baselines` blowing the same way (300 frames after 5 of warm-up). Prints CPU ms per frame and the
ratio HCIPy / eofnn (higher is better; the goal of issue "Any wind, ELT-class grids": >= 10 at 40 across, >= 5 at 80),
and the floor of this construction: the CPU time of the two steps every exact evaluation at this band needs (drawing
the random coefficients, the across-wind transforms) and the ratio they alone would allow.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import threadpoolctl
import torch

from benchmarks.baselines import HcipyTurbulence
from eofnn.sim.atmosphere import anywind
from eofnn.sim.atmosphere.turbulence import Atmosphere
from eofnn.sim.grid import ActuatorGrid


def measure(n_across: int, frames: int, repeats: int = 3) -> tuple[float, float, tuple[float, float]]:
    """``(hcipy, eofnn, (draws, transforms))`` CPU seconds per frame at ``n_across`` (8 m at 40 across, the same
    pitch at any size): each the least of ``repeats`` timings, HCIPy's and eofnn's interleaved (CPU time still moves
    by up to 2x on a shared machine; the least is the least disturbed)."""
    grid = ActuatorGrid(8.0 * n_across / 40, n_across, 0.0)
    atmosphere = Atmosphere(r0_m=0.083, r0_wavelength_m=6.58e-7, outer_scale_m=20.0, model="exact",
                            layers=[{"cn2_fraction": 1.0, "wind_speed_mps": 10.0, "wind_direction_deg": 30.0}])
    hcipy = HcipyTurbulence(atmosphere, grid, 1000.0)
    hcipy.frames(5)
    out = torch.empty(1024, grid.n_actuators, dtype=torch.float64)
    timings = []
    for _ in range(repeats):
        start = time.process_time()
        hcipy.frames(300)
        hcipy_s = (time.process_time() - start) / 300
        anywind._AMPLITUDE_CACHE.clear()  # a whole run: the amplitude table is built too
        start = time.process_time()
        layer = anywind.AnyWindFrozenFlow(grid, 0.083, 6.58e-7, 20.0, 10.0, 30.0, 1e-3, "subaperture", frames,
                                          np.random.SeedSequence(1))
        for first in range(0, frames - 1023, 1024):
            layer.write_frames(first, first + 1024, out)
        eofnn_s = (time.process_time() - start) / frames
        timings.append((hcipy_s, eofnn_s, *floor(layer, frames)))
    hcipy_s, eofnn_s, draws, transforms = (min(column) for column in zip(*timings, strict=True))
    return hcipy_s, eofnn_s, (draws, transforms)


def floor(layer: anywind.AnyWindFrozenFlow, frames: int) -> tuple[float, float]:
    """``(draws, transforms)`` CPU seconds per frame of the two steps no exact evaluation at this band avoids: drawing
    the screen's random coefficients (``n_coefficients`` complex numbers) and the across-wind type-2 transforms that
    take them to every position."""
    import finufft

    start = time.process_time()
    np.random.default_rng(2).standard_normal((layer.n_coefficients, 2), dtype=np.float32)
    draws = time.process_time() - start
    transforms = 0.0
    for _, across_period, amplitude in layer._amplitudes(*layer._spectrum_args):
        x = (2 * np.pi * layer._w / across_period).astype(np.float32)
        coefficients = amplitude.astype(np.complex64)
        start = time.process_time()
        finufft.nufft1d2(x, coefficients, eps=anywind._NUFFT_EPS, isign=1, nthreads=1)
        transforms += time.process_time() - start
    return draws / frames, transforms / frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=8192)
    parser.add_argument("--sizes", default="40,80")
    args = parser.parse_args()
    torch.set_num_threads(1)
    with threadpoolctl.threadpool_limits(1):
        measure(10, 1024, repeats=1)  # imports and first plans out of the timing
        for n in (int(s) for s in args.sizes.split(",")):
            hcipy_s, eofnn_s, (draws, transforms) = measure(n, args.frames)
            print(f"{n} across: HCIPy {hcipy_s * 1e3:.3f} ms/frame, eofnn whole run {eofnn_s * 1e3:.3f} ms/frame "
                  f"(CPU time, {args.frames} frames): ratio {hcipy_s / eofnn_s:.2f}; of it, drawing the coefficients "
                  f"{draws * 1e3:.3f} ms/frame and the across-wind transforms {transforms * 1e3:.3f} ms/frame: with "
                  f"nothing else, the ratio could reach {hcipy_s / (draws + transforms):.2f}")


if __name__ == "__main__":
    main()
