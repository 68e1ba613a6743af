"""``eofnn sweep``: a grid of ``compare`` runs, resumable, in local processes or as Ray tasks.

The subcommand's ``DESCRIPTION``, ``SweepConfig`` and ``sweep(cfg, config_dump) -> exit status`` are in
:mod:`eofnn.cli.sweep.command`; the pieces: :mod:`~eofnn.cli.sweep.grid` (grid files, points and their ids),
:mod:`~eofnn.cli.sweep.plan` (resolved and checked point configs), :mod:`~eofnn.cli.sweep.point` (one point on disk),
:mod:`~eofnn.cli.sweep.backends` (in process, worker processes, Ray), :mod:`~eofnn.cli.sweep.results` (sweep.csv)
and :mod:`~eofnn.reporting.sweep`.
"""

from eofnn.cli.sweep.command import DESCRIPTION, SweepConfig, sweep
from eofnn.cli.sweep.grid import expand, load_grid, parse_grid
from eofnn.cli.sweep.plan import Point, plan
from eofnn.cli.sweep.point import read_point, run_point

__all__ = ["DESCRIPTION", "Point", "SweepConfig", "expand", "load_grid", "parse_grid", "plan", "read_point",
           "run_point", "sweep"]
