"""The ``eofnn`` console script: imports nothing heavy before it can answer Ctrl-C or SIGTERM in one line.

Importing eofnn's subcommands pulls in torch, Lightning and HCIPy (seconds); a Ctrl-C or SIGTERM in those seconds
would otherwise end in an import traceback (:mod:`eofnn.cli.signals`).
"""

from __future__ import annotations

import sys

from eofnn.cli.signals import interruption, sigterm_as_interrupt


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
