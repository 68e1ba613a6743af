"""Where the points of a sweep run: in this process, in local worker processes, or as Ray tasks.

Every backend takes the same tasks ``(config_yaml, folder, threads)`` for :func:`~eofnn.cli.sweep.point.run_point` and
yields ``(index, result)`` as points finish, in whatever order they finish. A point's numbers depend only on its
config (seeds included) and the fixed torch thread count, never on the backend or the order.
"""

from __future__ import annotations

import itertools
import logging
import multiprocessing
import signal
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from eofnn.cli.sweep.point import first_line, record_failure, run_point
from eofnn.errors import ConfigError

BACKENDS = ("local", "ray")
Task = tuple[str, str, int]


def run_in_process(tasks: list[Task]) -> Iterator[tuple[int, dict]]:
    """One point after the other, in this process."""
    for index, task in enumerate(tasks):
        yield index, run_point(*task)


def _ignore_sigint() -> None:
    # Ctrl-C reaches the whole process group: the parent stops the workers itself, without their tracebacks.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_in_processes(tasks: list[Task], workers: int) -> Iterator[tuple[int, dict]]:
    """``workers`` spawned worker processes; at most one point per worker in flight.

    A worker that dies (killed, out of memory) breaks the pool: the points it and the others were running are
    recorded as failed (rerun on restart), and a fresh pool runs the rest.
    """
    before = set(multiprocessing.active_children())
    context = multiprocessing.get_context("spawn")

    def new_pool() -> ProcessPoolExecutor:
        return ProcessPoolExecutor(workers, mp_context=context, initializer=_ignore_sigint)

    queue = iter(enumerate(tasks))
    running: dict = {}
    pool = new_pool()
    finished = False
    try:
        while True:
            for index, task in itertools.islice(queue, workers - len(running)):
                running[pool.submit(run_point, *task)] = index
            if not running:
                break
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            broken = False
            for future in done:
                index = running.pop(future)
                try:
                    result = future.result()
                except BrokenProcessPool:
                    broken = True
                    result = record_failure(tasks[index][1], "a worker process died (killed or out of memory) while "
                                            "this point ran")
                yield index, result
            if broken:  # the pool fails every point still in it: record them and start a new pool
                wait(running)
                for index in list(running.values()):
                    yield index, record_failure(tasks[index][1], "the worker pool broke while this point ran")
                running.clear()
                pool.shutdown(wait=False)
                pool = new_pool()
        finished = True
    finally:
        if not finished:  # interrupted: stop the workers now rather than after their current points
            for process in set(multiprocessing.active_children()) - before:
                process.terminate()
        pool.shutdown(wait=finished, cancel_futures=True)


def run_on_ray(tasks: list[Task], workers: int, address: str | None = None) -> Iterator[tuple[int, dict]]:
    """Each point as a Ray task (one CPU each): on the cluster at ``address``, or on a local Ray of ``workers`` CPUs.

    Point folders must be on a file system every node sees. Ray retries a task whose worker or node died; a
    point that still fails is recorded as failed.
    """
    try:
        import ray
    except ImportError:
        raise ConfigError("backend='ray' needs Ray, which is not installed: pip install eofnn[ray]") from None
    started_here = not ray.is_initialized()
    if started_here:
        options = {"log_to_driver": False, "logging_level": logging.ERROR}
        try:
            if address:
                ray.init(address=address, **options)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, object_store_memory=256 * 2**20, **options)
        except (ConnectionError, ValueError, RuntimeError) as err:
            raise ConfigError(f"address={address!r}: Ray did not start: {first_line(err)}") from None
    remote = ray.remote(num_cpus=1)(run_point)
    pending = {remote.remote(*task): index for index, task in enumerate(tasks)}
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                index = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayError as err:
                    result = record_failure(tasks[index][1], f"ray: {first_line(err)}")
                yield index, result
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if started_here:
            ray.shutdown()


def run_tasks(tasks: list[Task], backend: str = "local", workers: int = 1,
              address: str | None = None) -> Iterator[tuple[int, dict]]:
    """Run ``tasks`` on ``backend`` (``local``: in process for one worker, else worker processes; ``ray``)."""
    if not tasks:
        return _nothing()
    if backend == "ray":
        return run_on_ray(tasks, workers, address)
    if address is not None:
        raise ConfigError(f"address={address!r} is only for backend='ray'")
    workers = min(workers, len(tasks))
    return run_in_process(tasks) if workers == 1 else run_in_processes(tasks, workers)


def _nothing() -> Iterator[tuple[int, dict]]:
    """No tasks: a generator all the same, so callers may ``close()`` whatever they were given."""
    yield from ()


def task(config_yaml: str, folder: Path, threads: int) -> Task:
    return config_yaml, str(Path(folder).resolve()), threads
