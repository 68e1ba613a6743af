"""Timing helpers and the result records every benchmark returns.

Every row compares an eofnn figure with a baseline timed *in the same run*, and the ratio is always
``baseline / eofnn`` (time per unit), so **higher is better** and ``> 1`` means eofnn is faster. Timings
alternate between the contenders (A, B, A, B, ...) so that background load hits both alike; each call is
repeated and the row keeps the min and the median over repeats. The headline ratio uses the minima (the least
disturbed estimate on a shared machine); the median ratio is kept beside it.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch


@dataclass
class Timing:
    """Seconds per unit (frame, step, fit, ...) of each repeat of one timed call."""

    seconds: list[float]

    @property
    def min(self) -> float:
        return float(min(self.seconds))

    @property
    def median(self) -> float:
        return float(np.median(self.seconds))


def synchronizer(device: str | torch.device) -> Callable[[], None]:
    """What to call before reading the clock: waits for the device's queued work (no-op on the CPU)."""
    device = torch.device(device)
    if device.type == "cuda":
        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def time_interleaved(calls: dict[str, tuple[Callable[[], object], float]], repeat: int, warmup: int = 1,
                     sync: Callable[[], None] | None = None) -> dict[str, Timing]:
    """Time several calls, alternating between them.

    Parameters
    ----------
    calls : dict
        ``name -> (fn, units)``: ``fn()`` does ``units`` units of work (frames, steps, ...); times are per unit.
    repeat : int
        Timed rounds; each round calls every function once, in order.
    warmup : int
        Untimed rounds first (caches, allocator, lazy initialisation).
    sync : callable, optional
        Called before each clock reading (``torch.cuda.synchronize`` for CUDA).
    """
    sync = sync or (lambda: None)
    out: dict[str, list[float]] = {name: [] for name in calls}
    for r in range(warmup + repeat):
        for name, (fn, units) in calls.items():
            sync()
            t0 = time.perf_counter()
            fn()
            sync()
            elapsed = time.perf_counter() - t0
            if r >= warmup:
                out[name].append(elapsed / units)
    return {name: Timing(seconds) for name, seconds in out.items()}


def time_once(fn: Callable[[], object], sync: Callable[[], None] | None = None) -> tuple[float, object]:
    """``(seconds, result)`` of one call."""
    sync = sync or (lambda: None)
    sync()
    t0 = time.perf_counter()
    result = fn()
    sync()
    return time.perf_counter() - t0, result


def copy_bandwidth(device: str = "cpu", n_bytes: int = 256 * 2**20, repeat: int = 5) -> float:
    """Bytes per second moved by ``Tensor.copy_`` of a large float64 buffer, reads plus writes (STREAM convention).

    A copy of ``n`` bytes reads ``n`` and writes ``n``, so the figure is ``2 n / t`` (minimum ``t`` over repeats).
    """
    n = max(n_bytes // 8, 1)
    src = torch.ones(n, dtype=torch.float64, device=device)
    dst = torch.empty_like(src)
    timing = time_interleaved({"copy": (lambda: dst.copy_(src), 1)}, repeat, warmup=1, sync=synchronizer(device))
    return 2 * n * 8 / timing["copy"].min


def loglog_exponent(x: list[float], y: list[float]) -> float:
    """Least-squares slope of ``log y`` against ``log x``: ``y ~ x**slope``."""
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


@dataclass
class Row:
    """One comparison: an eofnn figure against a baseline timed in the same run.

    ``ratio = baseline / eofnn`` from the minima over repeats (higher is better), ``ratio_median`` from the medians.
    ``goal_ratio`` is the smallest ratio that meets the goal (``None``: no goal, the row is for information).
    """

    benchmark: str
    name: str
    unit: str
    eofnn: Timing
    baseline: Timing
    baseline_label: str
    goal_ratio: float | None = None
    goal_label: str = ""
    device: str = "cpu"
    info: dict = field(default_factory=dict)

    @property
    def ratio(self) -> float:
        return self.baseline.min / self.eofnn.min

    @property
    def ratio_median(self) -> float:
        return self.baseline.median / self.eofnn.median

    @property
    def goal_met(self) -> bool | None:
        return None if self.goal_ratio is None else bool(self.ratio >= self.goal_ratio)

    def to_dict(self) -> dict:
        return {
            "benchmark": self.benchmark,
            "name": self.name,
            "device": self.device,
            "unit": self.unit,
            "eofnn_s": {"min": self.eofnn.min, "median": self.eofnn.median, "repeats": self.eofnn.seconds},
            "baseline": self.baseline_label,
            "baseline_s": {"min": self.baseline.min, "median": self.baseline.median,
                           "repeats": self.baseline.seconds},
            "ratio": self.ratio,
            "ratio_median": self.ratio_median,
            "goal": self.goal_label or None,
            "goal_ratio": self.goal_ratio,
            "goal_met": self.goal_met,
            "info": _jsonable(self.info),
        }


@dataclass
class Series:
    """How one time grows with one size: ``seconds[i]`` (min over repeats) at ``x[i]``, and the log-log slope."""

    benchmark: str
    name: str
    x_name: str
    x: list[float]
    seconds: list[float]
    unit: str
    goal_max_exponent: float | None = None
    goal_label: str = ""
    device: str = "cpu"
    info: dict = field(default_factory=dict)

    @property
    def exponent(self) -> float:
        return loglog_exponent(self.x, self.seconds)

    @property
    def ratios(self) -> list[float]:
        """Growth against the smallest size timed in the same run: ``seconds[i] / seconds[0]``."""
        return [s / self.seconds[0] for s in self.seconds]

    @property
    def goal_met(self) -> bool | None:
        return None if self.goal_max_exponent is None else bool(self.exponent <= self.goal_max_exponent)

    def to_dict(self) -> dict:
        return {
            "benchmark": self.benchmark,
            "name": self.name,
            "device": self.device,
            "x_name": self.x_name,
            "x": list(self.x),
            "unit": self.unit,
            "seconds": list(self.seconds),
            "ratios": self.ratios,
            "exponent": self.exponent,
            "goal": self.goal_label or None,
            "goal_max_exponent": self.goal_max_exponent,
            "goal_met": self.goal_met,
            "info": _jsonable(self.info),
        }


@dataclass
class Skipped:
    """A benchmark (or some of its rows) that did not run here, and why."""

    benchmark: str
    device: str
    reason: str

    def to_dict(self) -> dict:
        return asdict(self)


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, torch.Tensor):
        return value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def fmt_seconds(s: float) -> str:
    """Seconds with a readable unit."""
    if not math.isfinite(s):
        return str(s)
    for unit, scale in (("s", 1.0), ("ms", 1e-3), ("us", 1e-6), ("ns", 1e-9)):
        if abs(s) >= scale:
            return f"{s / scale:.3g} {unit}"
    return f"{s:.3g} s"


def fmt_value(value: float, unit: str) -> str:
    """A row's figure: bytes (rows whose unit is ``bytes``, e.g. peak memory) in B/kB/MB/GB, else seconds."""
    if unit != "bytes" or not math.isfinite(value):
        return fmt_seconds(value)
    for name, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if abs(value) >= scale:
            return f"{value / scale:.3g} {name}"
    return f"{value:.3g} B"


def status_bytes(field: str) -> int:
    """A memory field of ``/proc/self/status`` (``VmRSS``, ``VmHWM``...) in bytes (Linux). VmHWM (peak resident)
    belongs to this process image; ``ru_maxrss`` would carry a forking parent's over exec."""
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith(field + ":"))


def reset_peak_memory() -> None:
    """Reset VmHWM to the current resident size (Linux), so that the next peak is what follows, not the imports."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def sized_main(argv: list[str] | None, doc: str, frames: int, run: Callable[[int, int, int], list[Row]],
               describe: Callable[[dict], str]) -> list[dict]:
    """The command line of a benchmark sized by ``--frames`` (default ``frames``), ``--n-across`` (40) and
    ``--repeat`` (2): ``run(frames, n_across, repeat)``'s rows, a line each by ``describe``, then all as JSON."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--frames", type=int, default=frames)
    parser.add_argument("--n-across", type=int, default=40)
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args(argv)
    rows = [row.to_dict() for row in run(args.frames, args.n_across, args.repeat)]
    for row in rows:
        print(describe(row))
    print(json.dumps(rows, indent=1))
    return rows


#: The repository: where eofnn compare runs.
ROOT = Path(__file__).resolve().parent.parent


def timed_compare(config: Path, out: Path, extra: tuple[str, ...] = ()) -> tuple[float, float, float]:
    """``(wall s, CPU s, peak resident MB)`` of one fresh ``eofnn compare --config config`` process (``extra``: more
    arguments), its CPU the user and system time of the process and its children."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "eofnn.cli.main", "compare", "--config", str(config), *extra,
                           "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=3600)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"eofnn compare --config {config} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, after.ru_maxrss / 1024


def alternate_compares(jobs: dict[str, tuple[Path, tuple[str, ...]]], repeat: int) -> dict[str, list[tuple]]:
    """``{name: [(wall s, CPU s, peak MB) per repeat]}`` of ``jobs`` (``name -> (config, extra arguments)``), each a
    fresh :func:`timed_compare`, run in turn ``repeat`` times so that background load hits every job alike."""
    times: dict[str, list[tuple]] = {name: [] for name in jobs}
    with tempfile.TemporaryDirectory(prefix="eofnn-bench-compare-") as tmp:
        for r in range(repeat):
            for name, (config, extra) in jobs.items():
                times[name].append(timed_compare(config, Path(tmp) / f"{name}{r}", extra))
    return times
