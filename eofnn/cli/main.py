"""The ``eofnn`` command line: parse (:mod:`eofnn.cli.commands`), run, and answer bad input in one line.

Every value of a config can be overridden on the command line with its dotted key, e.g.
``--predictors.cl_eof.history_length 8`` or ``--scenario.atmosphere.r0_m 0.1``; the subcommands and their
configurations are in :mod:`eofnn.cli.commands`.
"""

from __future__ import annotations

import os
import sys
import warnings

from eofnn.cli.commands import USER_ERRORS, one_line, parse
from eofnn.cli.signals import INTERRUPTED, interruption, signal_seen, sigterm_as_interrupt
from eofnn.outputs import DISK_FULL


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings reach a user of the command line as one line each, without a source line."""
    print(f"eofnn: warning: {message}", file=sys.stderr)


def choose_backend() -> None:
    """Figures are files: the command line draws with matplotlib's Agg backend (no display needed), chosen here, the
    one place that does (no library module of eofnn chooses one on import). Without importing matplotlib when
    nothing has yet: ``eofnn --help`` stays light."""
    if "matplotlib" in sys.modules:
        sys.modules["matplotlib"].use("Agg")
    else:
        os.environ["MPLBACKEND"] = "Agg"


def _interrupted() -> int:
    what, status = interruption()
    print(f"eofnn: {what}: nothing was written (earlier results are untouched)", file=sys.stderr)
    return status


def main(args: list[str] | None = None) -> int:
    """Entry point of the ``eofnn`` console script; returns the exit status (2 bad input, 130 interrupted by Ctrl-C,
    143 terminated by SIGTERM, which is handled as Ctrl-C: :func:`eofnn.cli.signals.sigterm_as_interrupt`)."""
    args = list(sys.argv[1:] if args is None else args)
    choose_backend()
    # Lightning's banners, tips and warnings that say nothing to act on are quieted where eofnn runs its trainers
    # (eofnn.training.fit.quiet_lightning), so a program that calls eofnn from Python gets the same quiet.
    with sigterm_as_interrupt():
        try:
            with warnings.catch_warnings():
                warnings.showwarning = _show_warning
                # Parsing imports the subcommand's modules (seconds): inside the Ctrl-C handling below.
                status = parse(args).run()
        except USER_ERRORS as err:
            print(f"eofnn: error: {one_line(err)}", file=sys.stderr)
            return 2
        except OSError as err:
            if err.errno not in DISK_FULL:
                if signal_seen():
                    return _interrupted()
                raise
            # Outputs say which one (eofnn.outputs.OutputError); this is any other write (a temporary file).
            where = f" writing {err.filename!r}" if err.filename else ""
            print(f"eofnn: error: {err.strerror or 'no space left on device'}{where}: free some space and run again "
                  "(outputs are staged: earlier results are untouched)", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            return _interrupted()
        except Exception:
            if not signal_seen():
                raise
            return _interrupted()  # a signal inside an import surfaces as another error (RecursionError, ...)
    if status == INTERRUPTED:  # sweep answers an interruption itself (130): say which one it was
        status = interruption()[1]
    # A command may return its own exit status (sweep: 1 when some points failed); results are not statuses.
    return status if isinstance(status, int) and not isinstance(status, bool) else 0


if __name__ == "__main__":
    sys.exit(main())
