"""Benchmark: fitting from telemetry files larger than the memory given, read in blocks of frames.

    .venv/bin/python -m benchmarks.run --only stream            # ELT size: 5000 actuators, a 2 GB float32 file
    .venv/bin/python -m benchmarks.bench_stream --quick         # smoke size

An ELT-class loop records ~5000 actuators at 1 kHz (20 MB/s in float32). The telemetry is synthetic (the cost
does not depend on the values): ``y`` white (10 nm), ``wfs`` a random walk per actuator plus ``y``, float32 FITS
written block by block (never whole in memory), deleted afterwards.

- ``memory/<GB>``: peak resident memory added (``VmHWM`` in a fresh process, reset after the imports) by
  :func:`eofnn.training.from_telemetry.fit_from_telemetry` on a :class:`~eofnn.telemetry.file.StreamedTelemetry`
  of the big file (open-loop EOF, history 4, per actuator, ``batch_frames`` 256), against a memory budget of
  ``budget_fraction`` of the file. ``ratio = budget / peak`` (higher is better); goal >= 1: within the budget.
  ``info`` has the file size, the peak, and for contrast the peaks on the small file of the in-memory fit
  (``Telemetry.load`` + the same fit), the streamed one, and plant identification (``batch_frames`` 256) streamed
  and in memory, with the times.
- ``fit_time/<K>``: s per frame of the streamed fit (open + finiteness scan + fit) against the in-memory fit
  (``Telemetry.load`` + fit) of a small file that fits in memory, timed alternately in this process. Goal: within
  1.5x (ratio >= 0.67). ``info.max_relative_weight_difference`` checks they give the same filter.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import Row, Timing, reset_peak_memory, status_bytes, time_interleaved

ROOT = Path(__file__).resolve().parent.parent
SPEC = ("open_loop", 4, 2)


def write_fits(path: Path, n_frames: int, n_actuators: int, seed: int = 0, block_frames: int = 1024) -> int:
    """Write ``y`` and ``wfs`` (float32, ``(n_frames, n_actuators)``) block by block; returns the file's bytes."""
    from astropy.io import fits

    primary = fits.PrimaryHDU()
    primary.header["DELAY"] = SPEC[2]
    primary.header["FRATE"] = 1000.0
    primary.writeto(path)
    for name in ("Y", "WFS"):
        header = fits.ImageHDU(name=name).header
        header["BITPIX"], header["NAXIS"], header["NAXIS1"], header["NAXIS2"] = -32, 2, n_actuators, n_frames
        stream = fits.StreamingHDU(str(path), header)  # appends to an existing file (a str path only)
        walk = np.zeros(n_actuators, np.float32)
        for block, first in enumerate(range(0, n_frames, block_frames)):
            rng = np.random.default_rng([seed, block])
            frames = min(block_frames, n_frames - first)
            y = 10 * rng.standard_normal((frames, n_actuators), dtype=np.float32)
            s = walk + rng.standard_normal((frames, n_actuators), dtype=np.float32).cumsum(0)
            walk = s[-1]
            stream.write(y if name == "Y" else s + y)
        stream.close()
    return path.stat().st_size


def _fit(path: str, mode: str, batch_frames: int):
    """The fit measured: streamed (open, scan, fit) or in memory (load whole, fit); with ``identify_`` in front of
    the mode, plant identification instead."""
    from eofnn.data.history import HistorySpec
    from eofnn.telemetry.file import StreamedTelemetry
    from eofnn.telemetry.record import Telemetry
    from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry
    from eofnn.training.identify import identify_plant

    streamed = mode.endswith("streamed")
    telemetry = StreamedTelemetry.open(path) if streamed else Telemetry.load(path, required=("y", "wfs"))
    if mode.startswith("identify_"):
        return identify_plant(telemetry, batch_frames=batch_frames)
    return fit_from_telemetry(telemetry, HistorySpec(*SPEC), plant={"dm_gain": 1.0},
                              data=TelemetryDataConfig(batch_frames=batch_frames))


def _peak_child(path: str, mode: str, batch_frames: int) -> dict:
    """In a fresh process: resident memory before the fit and at its peak (Linux ``/proc/self/status``)."""
    import warnings

    warnings.simplefilter("ignore")
    import astropy.io.fits  # noqa: F401  (imports before the baseline reading)

    from eofnn.data.history import HistorySpec
    from eofnn.telemetry.record import Telemetry
    from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry

    # Lazy initialisation (torch kernels, Lightning's seeding) on 8 actuators: no buffer of the fit's size is kept.
    tiny = Telemetry(y=torch.randn(300, 8, dtype=torch.float64), wfs=torch.randn(300, 8, dtype=torch.float64))
    fit_from_telemetry(tiny, HistorySpec(*SPEC), plant={"dm_gain": 1.0}, data=TelemetryDataConfig(batch_frames=batch_frames))

    reset_peak_memory()  # the peak is the fit's, not the imports'
    before = status_bytes("VmRSS")
    t0 = time.perf_counter()
    fit = _fit(path, mode, batch_frames)
    seconds = time.perf_counter() - t0
    peak = status_bytes("VmHWM")
    return {"mode": mode, "rss_before_bytes": before, "peak_rss_bytes": peak, "peak_added_bytes": peak - before,
            "seconds": seconds, "result": getattr(fit, "train_loss", None) or getattr(fit, "dm_gain", None)}


def peak_memory(path: Path, mode: str, batch_frames: int) -> dict:
    code = ("import json, sys\nfrom benchmarks.bench_stream import _peak_child\n"
            "print(json.dumps(_peak_child(sys.argv[1], sys.argv[2], int(sys.argv[3]))))\n")
    out = subprocess.run([sys.executable, "-c", code, str(path), mode, str(batch_frames)], cwd=ROOT,
                         capture_output=True, text=True, check=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    return json.loads(out.stdout.strip().splitlines()[-1])


def bench_stream(n_actuators: int = 5000, big_frames: int = 50000, small_frames: int = 4000, batch_frames: int = 256,
                 budget_fraction: float = 0.125, repeat: int = 2, directory: str | None = None,
                 contrast: bool = True) -> list[Row]:
    """The two rows (module docstring); ``contrast``: also measure both fits' peaks on the small file."""
    with tempfile.TemporaryDirectory(dir=directory, prefix="eofnn-stream-") as folder:
        big, small = Path(folder) / "big.fits", Path(folder) / "small.fits"
        t0 = time.perf_counter()
        big_bytes = write_fits(big, big_frames, n_actuators, seed=1)
        write_s = time.perf_counter() - t0
        streamed_big = peak_memory(big, "streamed", batch_frames)
        big.unlink()  # disk back before the small runs
        small_bytes = write_fits(small, small_frames, n_actuators, seed=2)
        small_peaks = {mode: peak_memory(small, mode, batch_frames) for mode in
                       ("in_memory", "streamed", "identify_in_memory", "identify_streamed")} if contrast else {}
        fits = {}
        calls = {mode: (lambda mode=mode: fits.__setitem__(mode, _fit(str(small), mode, batch_frames)), small_frames)
                 for mode in ("streamed", "in_memory")}
        timings = time_interleaved(calls, repeat=repeat, warmup=1)
    weights = {mode: fit.network.weight.detach() for mode, fit in fits.items()}
    difference = float((weights["streamed"] - weights["in_memory"]).abs().max() / weights["in_memory"].abs().max())
    budget = budget_fraction * big_bytes
    gb = f"{big_bytes / 1e9:.3g}GB"
    memory = Row("stream", f"memory/{gb}", "bytes", Timing([float(streamed_big["peak_added_bytes"])]),
                 Timing([budget]), f"budget: {budget_fraction:g} of the file", goal_ratio=1.0,
                 goal_label=">= 1 (within the budget)",
                 info={"file_bytes": big_bytes, "n_actuators": n_actuators, "frames": big_frames, "dtype": "float32",
                       "batch_frames": batch_frames, "budget_bytes": budget, "write_s": write_s,
                       "streamed_big": streamed_big, "peak_over_file": streamed_big["peak_added_bytes"] / big_bytes,
                       "small_file_bytes": small_bytes, "small_file_peaks": small_peaks})
    time_row = Row("stream", f"fit_time/{n_actuators}", "s/frame", timings["streamed"], timings["in_memory"],
                   "Telemetry.load + the same fit", goal_ratio=0.67, goal_label=">= 0.67 (within 1.5x)",
                   info={"frames": small_frames, "file_bytes": small_bytes, "batch_frames": batch_frames,
                         "max_relative_weight_difference": difference, "threads": torch.get_num_threads()})
    return [memory, time_row]


QUICK = {"n_actuators": 80, "big_frames": 8000, "small_frames": 2000, "batch_frames": 256, "repeat": 1,
         "contrast": False}


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--dir", default=None, help="folder for the temporary files (default: the system's)")
    args = parser.parse_args(argv)
    rows = [row.to_dict() for row in bench_stream(**(QUICK if args.quick else {}), directory=args.dir)]
    print(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
