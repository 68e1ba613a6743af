"""Robustness maps: every controller, as made for the first scenario, run over a grid of plant errors.

The study's right-hand panel generalised: median RMS against DM gain (or any plant field; two fields give a map),
diverged points marked, and the analytic stability interval of each linear controller drawn over it.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from eofnn.errors import ConfigError  # noqa: E402
from eofnn.evaluation.experiment import Experiment  # noqa: E402
from eofnn.sim.plant import Plant  # noqa: E402
from eofnn.validation import Interval, check_value  # noqa: E402

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


def plot_robustness(result: RobustnessResult, path: Path) -> None:
    """1-D: median RMS against the plant field, diverged points as crosses on top, analytic DM gain bounds as
    dashed lines; 2-D: one map per controller with diverged cells crossed."""
    names = list(result.median_rms_nm)
    if len(result.keys) == 1:
        fig, ax = plt.subplots(figsize=(7.5, 5))
        x = np.asarray(result.values[0])
        finite = [v for vals in result.median_rms_nm.values() for v in vals if v is not None]
        top = max(finite) * 3 if finite else 1.0
        for i, name in enumerate(names):
            colour, style = f"C{i % 10}", ("-", "--", "-.", ":")[i % 4]
            y = np.array([np.nan if v is None else v for v in result.median_rms_nm[name]])
            ax.semilogy(x, y, marker="o", color=colour, linestyle=style, label=name)
            bad = np.isnan(y)
            if bad.any():
                ax.scatter(x[bad], np.full(bad.sum(), top * 1.4 ** i), marker="x", s=60, color=colour)
            if result.keys[0] == "dm_gain" and name in result.dm_gain_interval:
                for bound in result.dm_gain_interval[name]:
                    if bound is not None and x.min() <= bound <= x.max():
                        ax.axvline(bound, color=colour, linestyle=":", lw=1)
        ax.set_xlabel(result.keys[0])
        ax.set_ylabel("median RMS residual (nm)")
        ax.set_title(f"Robustness of the controllers made for '{result.scenario}'\n"
                     "crosses on top: diverged; dotted lines: analytic stability bounds")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=3, frameon=False)
    else:
        cols = min(len(names), 3)
        rows = -(-len(names) // cols)
        fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 4.2 * rows), squeeze=False)
        shape = (len(result.values[0]), len(result.values[1]))
        for ax, name in zip(axes.ravel(), names, strict=False):
            grid = np.array([np.nan if v is None else v for v in result.median_rms_nm[name]]).reshape(shape)
            image = ax.imshow(np.log10(grid.T), origin="lower", aspect="auto", cmap="viridis")
            for (i, j), v in np.ndenumerate(grid):
                if np.isnan(v):
                    ax.text(i, j, "×", ha="center", va="center", color="red", fontsize=12)
            ax.set_xticks(range(shape[0]), [f"{v:g}" for v in result.values[0]])
            ax.set_yticks(range(shape[1]), [f"{v:g}" for v in result.values[1]])
            ax.set_xlabel(result.keys[0])
            ax.set_ylabel(result.keys[1])
            ax.set_title(name)
            fig.colorbar(image, ax=ax, label="log10 median RMS (nm)")
        for ax in axes.ravel()[len(names):]:
            ax.set_visible(False)
        fig.suptitle(f"Robustness of the controllers made for '{result.scenario}' (×: diverged)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
