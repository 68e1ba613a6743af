"""The ``eofnn`` console script: imports nothing heavy before it can answer Ctrl-C or SIGTERM in one line.

Importing eofnn's subcommands pulls in torch, Lightning and HCIPy (seconds); a Ctrl-C in those seconds would
otherwise end in an import traceback.

SIGTERM (what ``timeout``, batch schedulers and Ray send) is handled as Ctrl-C: it raises ``KeyboardInterrupt`` in
the main thread, so staged outputs are removed and earlier results kept (:mod:`eofnn.outputs`); the run then exits
with :data:`TERMINATED` (143, 128 + SIGTERM, as a shell reports a process ended by it) instead of
:data:`INTERRUPTED` (130, Ctrl-C), so a scheduler can tell the two apart.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: Exit status after Ctrl-C (128 + SIGINT).
INTERRUPTED = 130
#: Exit status after SIGTERM (128 + SIGTERM).
TERMINATED = 143

_terminated = threading.Event()


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: an interruption like Ctrl-C (every ``except KeyboardInterrupt`` of eofnn handles it)."""


def _on_sigterm(signum, frame) -> None:
    if _terminated.is_set():
        return  # a second SIGTERM while the first one's clean-up runs: let it finish
    _terminated.set()
    raise Terminated


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
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def interruption() -> tuple[str, int]:
    """What ended the run, in words, and its exit status: SIGTERM (143) or Ctrl-C (130)."""
    return ("terminated (SIGTERM)", TERMINATED) if _terminated.is_set() else ("interrupted", INTERRUPTED)


def console() -> None:
    """Run :func:`eofnn.cli.main.main` and exit with its status (130 when interrupted, 143 when terminated, even while
    importing)."""
    with sigterm_as_interrupt():
        try:
            from eofnn.cli.main import main
        except KeyboardInterrupt:
            what, status = interruption()
            print(f"eofnn: {what}: nothing was written (earlier results are untouched)", file=sys.stderr)
            sys.exit(status)
        sys.exit(main())
