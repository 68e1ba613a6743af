"""``eofnn sweep``: a grid of ``compare`` runs, resumable, in local processes or as Ray tasks."""

from eofnn.sweep.cli import build_sweep_parser, run_sweep
from eofnn.sweep.grid import expand, load_grid, parse_grid
from eofnn.sweep.plan import Point, plan
from eofnn.sweep.point import read_point, run_point

__all__ = ["Point", "build_sweep_parser", "expand", "load_grid", "parse_grid", "plan", "read_point", "run_point",
           "run_sweep"]
