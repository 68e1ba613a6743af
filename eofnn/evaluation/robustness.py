"""Robustness maps: every controller, as made for the first scenario, run over a grid of plant errors.

The study's right-hand panel generalised: median RMS against DM gain (or any plant field; two fields give a map),
diverged points marked, and the analytic stability interval of each linear controller drawn over it.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass, field

import numpy as np

from eofnn.errors import ConfigError
from eofnn.evaluation.experiment import Experiment
from eofnn.sim.loop.plant import Plant
from eofnn.validation import Interval, check_value

#: Most grid points of one map (each runs every controller once).
MAX_POINTS = 400


def check_grid(grid: dict[str, list[float]] | None) -> dict[str, list[float]]:
    """A robustness grid: one or two numeric plant fields, each with a non-empty list of valid values."""
    if not grid:
        return {}
    if not isinstance(grid, dict) or len(grid) > 2:
        raise ConfigError(f"robustness={grid!r} is invalid: give one or two plant fields, each with a list of values")
    numeric = [name for name, c in Plant._constraints.items() if isinstance(c, Interval)]
    for name, values in grid.items():
        if name not in numeric:
            raise ConfigError(f"robustness key {name!r} is invalid: it must be one of {', '.join(numeric)}")
        if not isinstance(values, list) or not values:
            raise ConfigError(f"robustness.{name}={values!r} is invalid: give a non-empty list of values")
        for value in values:
            check_value(name, value, Plant._constraints[name], "robustness.")
    points = int(np.prod([len(v) for v in grid.values()]))
    if points > MAX_POINTS:
        raise ConfigError(f"robustness grid has {points} points: at most {MAX_POINTS} are allowed")
    return grid


@dataclass
class RobustnessResult:
    """Median RMS (``None`` where diverged) per controller and grid point, and the analytic DM gain intervals."""

    scenario: str
    keys: list[str]
    values: list[list[float]]
    median_rms_nm: dict[str, list[float | None]] = field(default_factory=dict)
    diverged_frame: dict[str, list[int | None]] = field(default_factory=dict)
    dm_gain_interval: dict[str, list[float | None]] = field(default_factory=dict)

    def points(self) -> list[tuple[float, ...]]:
        return list(itertools.product(*self.values))

    def to_json(self) -> str:
        return json.dumps({"scenario": self.scenario, "keys": self.keys, "values": self.values,
                           "points": self.points(), "median_rms_nm": self.median_rms_nm,
                           "diverged_frame": self.diverged_frame,
                           "analytic_dm_gain_interval": self.dm_gain_interval}, indent=1)


def robustness_map(experiment: Experiment, grid: dict[str, list[float]]) -> RobustnessResult:
    """Run every controller of ``experiment``, made for its first scenario, in each plant of ``grid``."""
    base_name, base = next(iter(experiment.scenarios.items()))
    result = RobustnessResult(base_name, list(grid), [list(map(float, v)) for v in grid.values()])
    for name in experiment.predictors:
        margins = experiment.stability(name, base_name)
        if margins is not None:
            result.dm_gain_interval[name] = margins["dm_gain_interval"]
        rms, diverged = [], []
        for point in result.points():
            variant = base.with_plant(**dict(zip(result.keys, point, strict=True)))
            m = experiment.evaluate(name, base_name, variant)
            rms.append(m.median_rms_nm)
            diverged.append(m.diverged_frame)
        result.median_rms_nm[name], result.diverged_frame[name] = rms, diverged
        experiment.log(f"  robustness {name:>18s}: {sum(d is not None for d in diverged)} of {len(diverged)} "
                       "plants diverged")
    return result
