"""``eofnn sweep``: many ``compare`` runs over a grid of config values, resumable, locally or on Ray.

    eofnn sweep --config configs/paper_small.yaml --grid experiments/sweeps/grid_history.yaml --out results/history
    eofnn sweep ... --workers 4                       # 4 local worker processes
    eofnn sweep ... --backend ray --address auto      # points as Ray tasks on a running cluster
    eofnn sweep ... --evaluation.frames 1500          # a dotted override of the base config, at every point

The output folder holds ``sweep.yaml`` (what was swept), ``points/<id>/`` (per point: ``point.yaml``, its
resolved config; ``run/``, compare's output; ``log.txt``; ``status.json``), ``sweep.csv`` and the figures.
Rerunning the same command resumes: finished points are kept, unfinished and failed ones rerun from scratch.
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
import threading
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml
from tqdm import tqdm

from eofnn.cli.common import Output
from eofnn.cli.sweep.backends import BACKENDS, run_tasks, task
from eofnn.cli.sweep.grid import load_grid
from eofnn.cli.sweep.plan import Point, plan
from eofnn.cli.sweep.point import INTERRUPTED, read_point, write_atomic
from eofnn.cli.sweep.results import CSV_FILE, write_csv
from eofnn.errors import ConfigError, require

SWEEP_FILE = "sweep.yaml"
POINTS_DIR = "points"


DESCRIPTION = ("Run one compare per point of a grid of config values (the Cartesian product of the grid's lists), "
               "each in its own folder; write sweep.csv and figures. Resumable: the same command again reruns only "
               "what did not finish. Exit status 0: all points done; 1: some failed (recorded); 2: bad input; "
               "130: interrupted.")


@dataclass(kw_only=True)
class SweepConfig(Output):
    """``eofnn sweep``: a grid of compare runs.

    Parameters
    ----------
    config : str
        Base compare config (YAML) that every point starts from.
    grid : str
        YAML mapping dotted config keys to lists or {log_range: [start, stop, count]}, e.g.
        predictors.cl_eof.history_length: [2, 4, 8].
    out : str
        Sweep folder: a new or empty one, or the folder of the same sweep to resume it.
    workers : int
        Points run at once (local: worker processes, 1 runs in this process; ray without --address: CPUs of the
        local Ray).
    backend : str
        local processes, or Ray tasks (pip install eofnn[ray]).
    address : str, optional
        Ray cluster to run on (e.g. auto or ray://host:10001); default: a local Ray.
    threads : int
        Torch threads per point (fixed, so numbers do not depend on the backend).
    overwrite : bool
        Discard the points and results of a previous sweep in --out and start again.
    progress : bool, optional
        Progress bar over points (default: only when stderr is a terminal).
    overrides : dict
        Dotted compare keys set at every point, after the base config, as compare's command line sets them:
        {evaluation.frames: 1500}. On the command line, any dotted option is one: --evaluation.frames 1500.
    """

    config: str
    grid: str
    workers: int = 1
    backend: Literal["local", "ray"] = "local"
    address: str | None = None
    threads: int = 1
    progress: bool | None = None
    overrides: dict[str, Any] = field(default_factory=dict)


def _log(message: str) -> None:
    tqdm.write(message, file=sys.stderr)


def _prepare_out(out: Path, overwrite: bool) -> None:
    """Make ``out`` ready: new, empty, a previous sweep to resume, or (``overwrite``) a previous sweep wiped."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"out={str(out)!r} is a file, not a folder")
    if overwrite and out.exists():
        shutil.rmtree(out / POINTS_DIR, ignore_errors=True)
        for path in [out / SWEEP_FILE, out / CSV_FILE, *out.glob("median_rms_*.png")]:
            path.unlink(missing_ok=True)
    elif out.exists() and any(out.iterdir()) and not (out / SWEEP_FILE).is_file():
        raise ConfigError(f"out={str(out)!r} is not empty and holds no sweep: choose another folder or pass "
                          "--overwrite true")
    try:
        (out / POINTS_DIR).mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"out={str(out)!r} cannot be created: {err.strerror or err}") from None
    if not os.access(out, os.W_OK | os.X_OK) or not os.access(out / POINTS_DIR, os.W_OK | os.X_OK):
        raise ConfigError(f"out={str(out)!r} is not writable: choose another folder")


def _check_options(cfg) -> None:
    require(cfg.workers >= 1, f"workers={cfg.workers!r} is invalid: it must be >= 1")
    require(cfg.threads >= 1, f"threads={cfg.threads!r} is invalid: it must be >= 1")
    require(cfg.backend in BACKENDS, f"backend={cfg.backend!r} is invalid: allowed are {', '.join(BACKENDS)}")
    if cfg.address is not None:
        require(cfg.backend == "ray", f"address={cfg.address!r} is only for --backend ray")


def sweep(cfg: SweepConfig, config_dump: str | None = None) -> int:
    """Run (or resume) the sweep ``cfg`` describes; returns the exit status.

    0: every point done; 1: some points failed (recorded in ``sweep.csv`` and their ``status.json``);
    130: interrupted (Ctrl-C), with ``sweep.csv`` consistent and finished points kept. Bad options or grids raise
    :class:`~eofnn.errors.ConfigError` before anything runs.
    """
    try:
        return _run(cfg)
    except KeyboardInterrupt:
        print("eofnn: interrupted before any point ran: rerun the same command to start", file=sys.stderr)
        return INTERRUPTED


def _settle(out: Path, points: list[Point], folders: dict[str, Path], results: dict[str, dict]) -> None:
    """After Ctrl-C: take in every point that finished on disk but had not reached the loop yet, then rewrite sweep.csv.

    A point is finished once its ``status.json`` is written; Ctrl-C can land between that and the loop's own
    update, so the table is rebuilt from the folders. A second Ctrl-C meanwhile is ignored: the table is always
    whole.
    """
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if threading.current_thread() is threading.main_thread() \
        else None
    try:
        for p in points:
            if p.id not in results and (r := read_point(folders[p.id], p.config_yaml)) is not None:
                results[p.id] = r
        write_csv(out / CSV_FILE, points, results)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def _run(cfg: SweepConfig) -> int:
    _check_options(cfg)
    grid = load_grid(cfg.grid)
    points = plan(cfg.config, grid, cfg.overrides)
    out = Path(cfg.out).resolve()
    _prepare_out(out, cfg.overwrite)
    folders = {p.id: out / POINTS_DIR / p.id for p in points}
    results = {p.id: r for p in points if (r := read_point(folders[p.id], p.config_yaml)) is not None}
    # Unchanged files are not rewritten: resuming a finished sweep touches nothing.
    record = {"config": str(Path(cfg.config).resolve()), "grid": grid, "points": len(points)}
    if cfg.overrides:  # only then: the record of a sweep without any stays as it was
        record["overrides"] = dict(cfg.overrides)
    write_atomic(out / SWEEP_FILE, yaml.safe_dump(record, sort_keys=False))
    write_csv(out / CSV_FILE, points, results)
    todo: list[Point] = [p for p in points if p.id not in results]
    if not todo and any(out.glob("median_rms_*.png")):
        _log(f"sweep: all {len(points)} points done, nothing to run; results in {out / CSV_FILE}")
        return 0
    where = f"{cfg.backend}" + (f" at {cfg.address}" if cfg.address else "")
    _log(f"sweep: {len(points)} points, {len(results)} already done, {len(todo)} to run ({where}, "
         f"{cfg.workers} worker{'s' * (cfg.workers > 1)})")
    progress = cfg.progress if cfg.progress is not None else sys.stderr.isatty()
    tasks = [task(p.config_yaml, folders[p.id], cfg.threads) for p in todo]
    failed = 0
    bar = tqdm(total=len(points), initial=len(results), unit="point", disable=not progress, file=sys.stderr)
    try:
        with bar, closing(run_tasks(tasks, cfg.backend, cfg.workers, cfg.address)) as finished:
            for index, result in finished:
                point = todo[index]
                results[point.id] = result
                write_csv(out / CSV_FILE, points, results)
                if result["status"] != "done":
                    failed += 1
                    _log(f"point {point.id} failed: {result['error']}")
                bar.update()
    except KeyboardInterrupt:
        _settle(out, points, folders, results)
        done = sum(r["status"] == "done" for r in results.values())
        print(f"eofnn: interrupted: {done} of {len(points)} points done, kept in {out}: rerun the same command to "
              "resume", file=sys.stderr)
        return INTERRUPTED
    from eofnn.reporting.sweep import plot_sweep  # matplotlib only when there is something to plot

    figures = plot_sweep(points, results, grid, out)
    _log(f"sweep: {len(points) - failed} of {len(points)} points done, {failed} failed; results in {out / CSV_FILE}"
         + (f" and {len(figures)} figures" if figures else ""))
    return 1 if failed else 0
