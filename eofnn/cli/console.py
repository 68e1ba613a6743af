"""The ``eofnn`` console script: imports nothing heavy before it can answer Ctrl-C in one line.

Importing eofnn's subcommands pulls in torch, Lightning and HCIPy (seconds); a Ctrl-C in those seconds would
otherwise end in an import traceback.
"""

from __future__ import annotations

import sys


def console() -> None:
    """Run :func:`eofnn.cli.main.main` and exit with its status (130 when interrupted, even while importing)."""
    try:
        from eofnn.cli.main import main
    except KeyboardInterrupt:
        print("eofnn: interrupted: nothing was written (earlier results are untouched)", file=sys.stderr)
        sys.exit(130)
    sys.exit(main())
