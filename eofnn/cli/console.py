"""The ``eofnn`` console script: imports nothing heavy before it can answer Ctrl-C or SIGTERM in one line.

Importing eofnn's subcommands pulls in torch, Lightning and HCIPy (seconds); a Ctrl-C or SIGTERM in those seconds
would otherwise end in an import traceback (:mod:`eofnn.cli.signals`).
"""

from __future__ import annotations

import sys

from eofnn.cli.signals import interruption, signal_seen, sigterm_as_interrupt


def console() -> None:
    """Run :func:`eofnn.cli.main.main` and exit with its status (130 when interrupted, 143 when terminated, even while
    importing)."""
    with sigterm_as_interrupt():
        try:
            from eofnn.cli.main import main
        except BaseException as err:
            # A signal inside an import can surface as another error (a half-imported module's RecursionError).
            if not (isinstance(err, KeyboardInterrupt) or signal_seen()):
                raise
            what, status = interruption()
            print(f"eofnn: {what}: nothing was written (earlier results are untouched)", file=sys.stderr)
            sys.exit(status)
        sys.exit(main())
