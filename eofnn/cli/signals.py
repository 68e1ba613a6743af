"""SIGTERM handled as Ctrl-C, and the exit statuses of an interrupted run.

SIGTERM (what ``timeout``, batch schedulers and Ray send) raises ``KeyboardInterrupt`` in the main thread, so staged
outputs are removed and earlier results kept (:mod:`eofnn.outputs`); the run then exits with :data:`TERMINATED` (143,
128 + SIGTERM, as a shell reports a process ended by it) instead of :data:`INTERRUPTED` (130, Ctrl-C), so a
scheduler can tell the two apart. Imports nothing heavy: the console script installs it before eofnn's subcommands
load.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: Exit status after Ctrl-C (128 + SIGINT).
INTERRUPTED = 130
#: Exit status after SIGTERM (128 + SIGTERM).
TERMINATED = 143

_terminated = threading.Event()
_interrupted = threading.Event()


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: an interruption like Ctrl-C (every ``except KeyboardInterrupt`` of eofnn handles it)."""


def _on_sigterm(signum, frame) -> None:
    if _terminated.is_set():
        return  # a second SIGTERM while the first one's clean-up runs: let it finish
    _terminated.set()
    raise Terminated


def _on_sigint(signum, frame) -> None:
    _interrupted.set()  # remembered: a KeyboardInterrupt raised inside an import can surface as another error
    raise KeyboardInterrupt


def signal_seen() -> bool:
    """Whether Ctrl-C or SIGTERM reached this run: then whatever error ends it (a module left half-imported by the
    interruption raises ``RecursionError``, say) is the interruption's doing, and is reported as one."""
    return _terminated.is_set() or _interrupted.is_set()


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """While the block runs, SIGTERM raises :class:`Terminated` (a ``KeyboardInterrupt``) in the main thread; the
    previous handler is put back afterwards. Outside the main thread (where Python cannot set handlers) nothing
    changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if signal.getsignal(signal.SIGTERM) is not _on_sigterm:
        _terminated.clear()  # a new run (main() called again in one process); nested blocks keep what was seen
        _interrupted.clear()
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    previous_int = signal.getsignal(signal.SIGINT)
    if previous_int is signal.default_int_handler:  # the default: KeyboardInterrupt, now also remembered
        signal.signal(signal.SIGINT, _on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        if previous_int is signal.default_int_handler:
            signal.signal(signal.SIGINT, previous_int)


def interruption() -> tuple[str, int]:
    """What ended the run, in words, and its exit status: SIGTERM (143) or Ctrl-C (130)."""
    return ("terminated (SIGTERM)", TERMINATED) if _terminated.is_set() else ("interrupted", INTERRUPTED)
