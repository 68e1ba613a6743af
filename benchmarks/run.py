"""Run every benchmark, print a table of ratios against baselines timed in the same run, and write JSON.

    .venv/bin/python -m benchmarks.run                 # full run (several minutes on 2 cores)
    .venv/bin/python -m benchmarks.run --quick         # everything at tiny size, in seconds
    .venv/bin/python -m benchmarks.run --only fit,loop --out /tmp/fit.json

Ratios are ``baseline / eofnn`` (higher is better; ``> 1``: eofnn faster). See ``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import subprocess
import sys
import time
import traceback
import warnings
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import Series, Skipped, fmt_value

ROOT = Path(__file__).resolve().parent.parent
REFERENCE_CONFIG = ROOT / "configs" / "reference.yaml"
BENCHMARKS = ("turbulence", "exact", "loop", "fit", "stability", "end_to_end", "scaling", "stream", "startup",
              "flagship", "pyramid")
#: Benchmarks whose functions take a ``device``; the others are CPU code in eofnn (HCIPy, numpy, the loop).
DEVICE_BENCHMARKS = ("loop", "fit")

#: Sizes of the full run (the figures in the README) and of ``--quick`` (a smoke run of every code path).
FULL = {
    "turbulence": {"n_across": (40, 80), "chunk_frames": 1024, "chunks_per_repeat": 10, "hcipy_frames": 500,
                   "repeat": 5, "setup_repeat": 3},
    "exact": {"n_across": (40, 80), "chunk_frames": 1024, "chunks_per_repeat": 8, "hcipy_frames": 400, "repeat": 3,
              "stream_frames": 100_000, "stream_across": 40},
    "loop": {"n_across": (40, 80), "history_length": 12, "n_frames": 2000, "step_count": 2000, "repeat": 5},
    "fit": {"n_frames": 60000, "n_actuators": 1264, "n_taps": 12, "repeat": 3,
            "elt": {"n_frames": 60000, "n_actuators": 5024, "n_taps": 12, "pool_frames": 4000, "repeat": 2}},
    "stability": {"n_actuators": (1264, 5024), "history_length": 6, "repeat": 3, "goal_seconds": 10.0,
                  "coupled": {"n_across": 40, "history_length": 10, "train_frames": 4000, "val_frames": 1000,
                              "repeat": 1, "budget_seconds": 300.0}},
    "end_to_end": {"diameter_m": 4.0, "n_across": 20, "history_length": 4, "train_frames": 20000,
                   "val_frames": 2000, "eval_frames": 5000, "repeat": 2},
    "scaling": {},
    "stream": {"n_actuators": 5000, "big_frames": 50000, "small_frames": 4000, "batch_frames": 256, "repeat": 2},
    "startup": {"repeat": 7},
    "flagship": {"repeat": 1},
    "pyramid": {"repeat": 1},
}
QUICK = {
    "turbulence": {"n_across": (8, 10), "chunk_frames": 100, "chunks_per_repeat": 2, "hcipy_frames": 50, "repeat": 2,
                   "setup_repeat": 1},
    "exact": {"n_across": (8, 10), "chunk_frames": 100, "chunks_per_repeat": 2, "hcipy_frames": 50, "repeat": 2,
              "stream_frames": 1000, "stream_across": 8},
    "loop": {"n_across": 10, "history_length": 12, "n_frames": 200, "step_count": 200, "repeat": 2,
             "bandwidth_bytes": 16 * 2**20},
    "fit": {"n_frames": 2000, "n_actuators": 80, "n_taps": 12, "batch_frames": (256, 1024), "repeat": 2,
            "elt": {"n_frames": 2000, "n_actuators": 76, "n_taps": 12, "pool_frames": 500, "repeat": 1}},
    "stability": {"n_actuators": (76,), "history_length": 6, "repeat": 1, "goal_seconds": 10.0,
                  # 8 across: 52 actuators, 260 companion rows, the same dense code paths as 10 across's 80 and 400
                  # rows, in 5.6 s of CPU against 11.4 s (of --quick's 40 s: each method's dense eigvals dominate).
                  "coupled": {"n_across": 8, "history_length": 4, "train_frames": 400, "val_frames": 200,
                              "repeat": 1, "budget_seconds": 300.0}},
    "end_to_end": {"diameter_m": 2.0, "n_across": 10, "history_length": 4, "train_frames": 1000, "val_frames": 200,
                   "eval_frames": 300, "repeat": 1, "warmup": 0},
    "scaling": {"n_across": (6, 8, 10), "histories": (2, 4, 8), "turbulence_frames": (400, 800, 1600),
                "stream_chunk": 200, "call_frames": (100, 200, 400), "chunk_frames": 200, "loop_frames": 100,
                "steps": 100, "fit_frames": (500, 1000, 2000),
                "fit_actuator_frames": 500, "fit_history_frames": 500, "base_across": 10, "repeat": 1,
                "compare_across": (6, 8, 10), "compare_train_frames": 400, "compare_eval_frames": 300},
    "stream": {"n_actuators": 80, "big_frames": 8000, "small_frames": 2000, "batch_frames": 256, "repeat": 1,
               "contrast": False},
    "startup": {"repeat": 1, "warmup": 0},
    "flagship": {"repeat": 1, "quick": True},
    "pyramid": {"repeat": 1, "quick": True},
}


def with_model(scenario, model: str):
    """The scenario with another turbulence model (its own default sensing kernel)."""
    atmosphere = dataclasses.replace(scenario.atmosphere, model=model, kernel=None)
    return dataclasses.replace(scenario, atmosphere=atmosphere)


def run_benchmark(name: str, scenario, sizes: dict, device: str) -> tuple[list, list]:
    """``(rows or series, skipped)`` of one benchmark on one device."""
    if name == "turbulence":
        from benchmarks.bench_turbulence import bench_turbulence

        # The B-spline strip model (configs/reference.yaml is the study's hcipy_pupil: HCIPy against itself).
        return bench_turbulence(with_model(scenario, "strip"), **sizes), []
    if name == "exact":
        from benchmarks.bench_exact import bench_exact

        return bench_exact(scenario, **sizes), []
    if name == "loop":
        from benchmarks.bench_loop import bench_loop

        rows, skipped = [], []
        sizes = dict(sizes)
        across = sizes.pop("n_across")
        for n in across if isinstance(across, tuple) else (across,):  # 80 across: an ELT's 5024 actuators
            more_rows, more_skipped = bench_loop(scenario, n_across=n, device=device, **sizes)
            rows, skipped = rows + more_rows, skipped + more_skipped
        return rows, skipped
    if name == "fit":
        from benchmarks.bench_fit import bench_fit, bench_fit_pooled

        sizes = dict(sizes)
        elt = sizes.pop("elt", None)
        rows, skipped = bench_fit(device=device, **sizes)
        if elt is not None:  # 60k frames at 5024 actuators: more than memory holds, so a pool read over and over
            more_rows, more_skipped = bench_fit_pooled(device=device, **elt)
            rows, skipped = rows + more_rows, skipped + more_skipped
        return rows, skipped
    if name == "stability":
        from benchmarks.bench_adaptive import stability_rows
        from benchmarks.bench_coupled import coupled_rows

        rows = [row for n in sizes["n_actuators"]
                for row in stability_rows(n, sizes["history_length"], sizes["repeat"], 0, "stability",
                                          f"analysis/{n}", sizes["goal_seconds"])]
        return rows + coupled_rows(**sizes["coupled"]), []
    if name == "end_to_end":
        from benchmarks.bench_end_to_end import bench_end_to_end, small_reference_scenario

        sizes = dict(sizes)
        # What a user gets by default: the exact model seen through each subaperture.
        small = small_reference_scenario(with_model(scenario, "exact"), sizes.pop("diameter_m"), sizes.pop("n_across"))
        return bench_end_to_end(small, **sizes), []
    if name == "scaling":
        from benchmarks.bench_scaling import bench_scaling

        return bench_scaling(with_model(scenario, "strip"), **sizes), []
    if name == "stream":
        from benchmarks.bench_stream import bench_stream

        return bench_stream(**sizes), []
    if name == "startup":
        from benchmarks.bench_startup import bench_startup

        return bench_startup(**sizes), []
    if name == "flagship":
        from benchmarks.bench_flagship import bench_flagship

        return bench_flagship(**sizes), []
    if name == "pyramid":
        from benchmarks.bench_pyramid import bench_pyramid

        return bench_pyramid(**sizes), []
    raise ValueError(f"unknown benchmark {name!r}: allowed are {', '.join(BENCHMARKS)}")


def machine_info() -> dict:
    """What the figures were measured on."""
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                                timeout=10).stdout.strip() or None
        # Uncommitted changes to the code under test: the commit alone does not say what was measured then.
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "eofnn"], cwd=ROOT, capture_output=True,
                               text=True, timeout=10).stdout.split("\n")
        dirty = [line[3:] for line in dirty if line.strip()]
    except (OSError, subprocess.SubprocessError):
        commit, dirty = None, None
    import hcipy

    return {
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "hcipy": hcipy.__version__,
        "cuda_available": torch.cuda.is_available(),
        "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "git_commit": commit,
        "eofnn_uncommitted_changes": dirty,
        "load_average_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def _cpu_seconds() -> tuple[float, float] | None:
    """``(busy CPU seconds of the whole machine, CPU seconds of this process and its waited-for children)``, or None
    off Linux (a benchmark that times ``eofnn`` in child processes must not count them as other processes')."""
    try:
        import resource

        fields = [float(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
        busy = (sum(fields[:8]) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")  # all but idle and iowait
        own = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
        return busy, sum(r.ru_utime + r.ru_stime for r in own)
    except (OSError, ValueError, ImportError, IndexError):
        return None


def wait_until_quiet(max_wait_s: float, threshold: float = 0.1, window_s: float = 3.0) -> float:
    """Wait (at most ``max_wait_s``) until other processes use under ``threshold`` of the CPUs for ``window_s``.

    Returns the seconds waited. On a shared machine this keeps a benchmark from starting in the middle of
    someone else's test run; it cannot stop one from starting later (``other_load`` in the JSON tells).
    """
    t0 = time.perf_counter()
    while True:
        a = _cpu_seconds()
        time.sleep(window_s)
        b = _cpu_seconds()
        if a is None or b is None:
            return 0.0
        other = ((b[0] - a[0]) - (b[1] - a[1])) / (window_s * (os.cpu_count() or 1))
        waited = time.perf_counter() - t0
        if other < threshold or waited >= max_wait_s:
            return waited


def run_all(quick: bool = False, only: tuple[str, ...] = BENCHMARKS, devices: tuple[str, ...] = ("cpu", "cuda"),
            log: Callable[[str], None] = print, wait_quiet_s: float = 0.0) -> dict:
    """Run the benchmarks; the JSON-ready results (``meta``, ``rows``, ``scaling``, ``skipped``, ``errors``)."""
    from eofnn.sim.scenario import Scenario

    sizes = QUICK if quick else FULL
    scenario = Scenario.from_yaml(REFERENCE_CONFIG)
    results = {"meta": dict(machine_info(), quick=quick, reference_config=str(REFERENCE_CONFIG.relative_to(ROOT))),
               "rows": [], "scaling": [], "skipped": [], "errors": [], "seconds": {}, "other_load": {},
               "waited_for_quiet_s": {}}
    for name in only:
        for device in devices if name in DEVICE_BENCHMARKS else ("cpu",):
            if torch.device(device).type == "cuda" and not torch.cuda.is_available():
                skip = Skipped(name, device, "torch.cuda.is_available() is False")
                results["skipped"].append(skip.to_dict())
                log(f"[{name}/{device}] skipped: {skip.reason}")
                continue
            if wait_quiet_s > 0:
                waited = wait_until_quiet(wait_quiet_s)
                results["waited_for_quiet_s"][f"{name}/{device}"] = waited
                if waited > 5:
                    log(f"[{name}/{device}] waited {waited:.0f} s for other processes to quieten")
            log(f"[{name}/{device}] running ...")
            t0, cpu0 = time.perf_counter(), _cpu_seconds()
            try:
                items, skipped = run_benchmark(name, scenario, sizes[name], device)
            except Exception as err:  # one failing benchmark must not hide the others
                results["errors"].append({"benchmark": name, "device": device,
                                          "error": f"{type(err).__name__}: {err}",
                                          "traceback": traceback.format_exc()})
                log(f"[{name}/{device}] FAILED: {type(err).__name__}: {err}")
                continue
            finally:
                wall, cpu1 = time.perf_counter() - t0, _cpu_seconds()
                results["seconds"][f"{name}/{device}"] = wall
                if cpu0 is not None and cpu1 is not None:
                    # CPU used by other processes while this benchmark ran, as a fraction of all cores: the
                    # figures of a benchmark that shared the machine (> ~0.1) are less trustworthy.
                    other = (cpu1[0] - cpu0[0]) - (cpu1[1] - cpu0[1])
                    results["other_load"][f"{name}/{device}"] = max(other, 0.0) / (wall * (os.cpu_count() or 1))
            for item in items:
                key = "scaling" if isinstance(item, Series) else "rows"
                results[key].append(item.to_dict())
            for skip in skipped:
                results["skipped"].append(skip.to_dict())
                log(f"[{name}/{device}] partly skipped: {skip.reason}")
            load = results["other_load"].get(f"{name}/{device}")
            log(f"[{name}/{device}] done in {results['seconds'][f'{name}/{device}']:.1f} s"
                + (f" (other processes used {load:.0%} of the CPUs meanwhile)" if load is not None else ""))
    results["meta"]["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    return results


def _met(value) -> str:
    return "-" if value is None else ("yes" if value else "NO")


def format_table(results: dict) -> str:
    """The rows and the scaling series as plain-text tables."""
    lines = ["Ratios are baseline / eofnn from the minimum over repeats (median-based in brackets): higher is better.",
             ""]
    header = ("benchmark", "row", "dev", "eofnn", "baseline", "baseline is", "ratio", "(median)", "goal", "met")
    table = [header]
    for r in results["rows"]:
        table.append((r["benchmark"], r["name"], r["device"], fmt_value(r["eofnn_s"]["min"], r["unit"]),
                      fmt_value(r["baseline_s"]["min"], r["unit"]), r["baseline"], f"{r['ratio']:.3g}",
                      f"({r['ratio_median']:.3g})", r["goal"] or "", _met(r["goal_met"])))
    lines += _columns(table)
    if results["scaling"]:
        lines += ["", "Scaling: time at each size (growth against the smallest size), log-log exponent."]
        table = [("series", "x", "sizes", "times", "growth", "exponent", "goal", "met")]
        for s in results["scaling"]:
            table.append((s["name"], s["x_name"], " ".join(f"{x:g}" for x in s["x"]),
                          " ".join(fmt_value(t, s["unit"]).replace(" ", "") for t in s["seconds"]),
                          " ".join(f"{g:.3g}" for g in s["ratios"]), f"{s['exponent']:.2f}", s["goal"] or "",
                          _met(s["goal_met"])))
        lines += _columns(table)
    if results.get("other_load"):
        lines += ["", "CPU used by other processes during each benchmark (fraction of all cores; > 0.1 means the "
                      "machine was shared and the figures are less trustworthy):",
                  "  " + ", ".join(f"{k}: {v:.2f}" for k, v in results["other_load"].items())]
    if results["skipped"]:
        lines += ["", "Skipped:"] + [f"  {s['benchmark']}/{s['device']}: {s['reason']}" for s in results["skipped"]]
    if results["errors"]:
        lines += ["", "ERRORS:"] + [f"  {e['benchmark']}/{e['device']}: {e['error']}" for e in results["errors"]]
    return "\n".join(lines)


def _columns(table: list[tuple]) -> list[str]:
    widths = [max(len(str(row[i])) for row in table) for i in range(len(table[0]))]
    out = ["  ".join(str(v).ljust(w) for v, w in zip(row, widths, strict=True)).rstrip() for row in table]
    out.insert(1, "  ".join("-" * w for w in widths))
    return out


def check_results(results: dict) -> list[str]:
    """Problems that make a results file unusable: missing benchmarks, non-finite or non-positive ratios, errors."""
    problems = [f"error in {e['benchmark']}/{e['device']}: {e['error']}" for e in results["errors"]]
    for r in results["rows"]:
        for key in ("ratio", "ratio_median"):
            if not (isinstance(r[key], float) and math.isfinite(r[key]) and r[key] > 0):
                problems.append(f"{r['benchmark']}/{r['name']}: {key}={r[key]!r}")
    for s in results["scaling"]:
        if not math.isfinite(s["exponent"]) or not all(math.isfinite(g) and g > 0 for g in s["ratios"]):
            problems.append(f"scaling/{s['name']}: exponent={s['exponent']!r}, ratios={s['ratios']!r}")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes: every code path in seconds")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON file (default: benchmarks/results.json, or benchmarks/results_quick.json with "
                             "--quick)")
    parser.add_argument("--only", default=",".join(BENCHMARKS),
                        help=f"comma-separated subset of {', '.join(BENCHMARKS)}")
    parser.add_argument("--devices", default="cpu,cuda",
                        help="devices for the benchmarks that take one (loop, fit); CUDA is skipped when absent")
    parser.add_argument("--wait-quiet", type=float, default=0.0, metavar="SECONDS",
                        help="before each benchmark, wait up to SECONDS until other processes leave the CPUs idle "
                             "(for shared machines; default: do not wait)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch intra-op threads (default: torch's own choice, recorded in the JSON)")
    args = parser.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    only = tuple(name.strip() for name in args.only.split(",") if name.strip())
    unknown = sorted(set(only) - set(BENCHMARKS))
    if unknown:
        parser.error(f"unknown benchmark(s) {', '.join(unknown)}: allowed are {', '.join(BENCHMARKS)}")
    out = args.out or Path(__file__).resolve().parent / ("results_quick.json" if args.quick else "results.json")
    devices = tuple(d.strip() for d in args.devices.split(",") if d.strip())

    with warnings.catch_warnings():
        # Lightning's advice and deprecation chatter inside fit_predictor, not about the figures.
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        warnings.filterwarnings("ignore", message=".*LeafSpec.*")
        results = run_all(args.quick, only, devices, log=lambda msg: print(msg, file=sys.stderr, flush=True),
                          wait_quiet_s=args.wait_quiet)
    print(format_table(results))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"\nwritten to {out}")
    problems = check_results(results)
    for problem in problems:
        print(f"problem: {problem}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
