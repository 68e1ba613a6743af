"""Figures of a sweep: the median RMS residual against each swept key, and a heat map when two keys are swept.

Against one key, each predictor is one line (one panel per scenario); where other keys are swept too, each
value shows the *best* (lowest) median RMS over the other keys' values, and the title says so. Diverged or
failed points leave gaps. The heat map (two keys) has one panel per scenario and predictor whose result
changes across the grid (baselines that do not depend on the swept keys are left out).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LogNorm

#: A sweep's point: ``id`` (its folder name) and ``values`` (swept key -> value), as ``eofnn.cli.sweep.plan.Point``.
Point = Any

METRIC = "median_rms_nm"
METRIC_LABEL = "median RMS residual (nm)"
MAX_HEATMAP_PANELS = 12


def metric(result: dict | None, scenario: str, predictor: str, name: str = "median_rms_nm") -> float:
    """One metric of a point's result, NaN where the point failed, is pending or the loop diverged."""
    try:
        value = result["scenarios"][scenario][predictor][name]
    except (TypeError, KeyError):
        return math.nan
    return math.nan if value is None else float(value)


def runs(results: dict[str, dict]) -> list[tuple[str, str]]:
    """Every ``(scenario, predictor)`` of the finished points, in the order compare wrote them."""
    seen: dict[tuple[str, str], None] = {}
    for result in results.values():
        for scenario, predictors in (result.get("scenarios") or {}).items():
            for predictor in predictors:
                seen[(scenario, predictor)] = None
    return list(seen)


def _same(a: Any, b: Any) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def _numeric(values: list[Any]) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def _label(value: Any, max_chars: int = 24) -> str:
    text = f"{value:g}" if isinstance(value, float) else str(value)
    return text if len(text) <= max_chars else text[: max_chars - 3] + "..."


def _file_name(key: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.\-]+", "-", key)


def _best(points: list[Point], results: dict, key: str, value: Any, scenario: str, predictor: str) -> float:
    found = [metric(results.get(p.id), scenario, predictor, METRIC) for p in points if _same(p.values[key], value)]
    finite = [v for v in found if math.isfinite(v)]
    return min(finite) if finite else math.nan


def _set_x(ax, key: str, values: list[Any]) -> list[Any]:
    """Positions of ``values`` on the x axis (log for positive numbers spanning 50x or more, else categorical)."""
    ax.set_xlabel(key)
    if _numeric(values):
        if min(values) > 0 and max(values) / min(values) >= 50:
            ax.set_xscale("log")
        if len(values) <= 10:  # ticks at the swept values themselves, not at 2.25, 2.5, ...
            ax.set_xticks(values, [_label(v) for v in values])
            ax.minorticks_off()
        return list(values)
    ax.set_xticks(range(len(values)), [_label(v) for v in values])
    return list(range(len(values)))


def plot_against_key(points: list[Point], results: dict, grid: dict[str, list[Any]], key: str, path: Path) -> None:
    """Median RMS against ``key``: one panel per scenario, one line per predictor, log y."""
    pairs = runs(results)
    scenarios = list(dict.fromkeys(s for s, _ in pairs))
    others = [k for k in grid if k != key and len(grid[k]) > 1]
    fig, axes = plt.subplots(1, len(scenarios), figsize=(5.2 * len(scenarios) + 1.8, 4.2), squeeze=False)
    for ax, scenario in zip(axes[0], scenarios, strict=True):
        x = _set_x(ax, key, grid[key])
        for predictor in [p for s, p in pairs if s == scenario]:
            y = [_best(points, results, key, v, scenario, predictor) for v in grid[key]]
            ax.plot(x, y, "o-", label=predictor)
        ax.set_yscale("log")
        ax.set_ylabel(METRIC_LABEL)
        ax.set_title(f"scenario {scenario}")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small")
    note = f"\n(each value: the best over {', '.join(others)})" if others else ""
    fig.suptitle(f"{METRIC_LABEL} against {key}{note}", fontsize="medium")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _varies(values: np.ndarray) -> bool:
    finite = values[np.isfinite(values)]
    return finite.size > 0 and (finite.size < values.size or not np.allclose(finite, finite[0], rtol=1e-9, atol=0))


def plot_heatmap(points: list[Point], results: dict, grid: dict[str, list[Any]], path: Path) -> None:
    """Median RMS over the two swept keys: one panel per scenario and predictor that changes across the grid."""
    rows_key, cols_key = list(grid)
    row_values, col_values = grid[rows_key], grid[cols_key]
    maps = {}
    for scenario, predictor in runs(results):
        grid_map = np.full((len(row_values), len(col_values)), np.nan)
        for point in points:
            i = next(n for n, v in enumerate(row_values) if _same(v, point.values[rows_key]))
            j = next(n for n, v in enumerate(col_values) if _same(v, point.values[cols_key]))
            grid_map[i, j] = metric(results.get(point.id), scenario, predictor, METRIC)
        maps[(scenario, predictor)] = grid_map
    shown = {k: m for k, m in maps.items() if _varies(m)} or maps
    shown = dict(list(shown.items())[:MAX_HEATMAP_PANELS])
    n = len(shown)
    n_cols = min(n, 3)
    n_rows = math.ceil(n / n_cols)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(4.6 * n_cols, 3.9 * n_rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    for ax, ((scenario, predictor), grid_map) in zip(axes.flat, shown.items(), strict=False):
        finite = grid_map[np.isfinite(grid_map) & (grid_map > 0)]
        norm = LogNorm(finite.min(), finite.max()) if finite.size and finite.min() < finite.max() else None
        image = ax.imshow(np.ma.masked_invalid(grid_map), origin="lower", aspect="auto", cmap="viridis", norm=norm)
        ax.set_facecolor("0.85")  # gaps (diverged, failed) in grey
        for (i, j), value in np.ndenumerate(grid_map):
            text = f"{value:.3g}" if math.isfinite(value) else "n/a"
            ax.text(j, i, text, ha="center", va="center", fontsize="x-small",
                    color="white" if math.isfinite(value) and norm is not None and norm(value) < 0.5 else "black")
        ax.set_xticks(range(len(col_values)), [_label(v) for v in col_values], fontsize="small")
        ax.set_yticks(range(len(row_values)), [_label(v) for v in row_values], fontsize="small")
        ax.set_xlabel(cols_key, fontsize="small")
        ax.set_ylabel(rows_key, fontsize="small")
        ax.set_title(f"{predictor} in {scenario}", fontsize="medium")
        fig.colorbar(image, ax=ax, label="nm")
    fig.suptitle(f"{METRIC_LABEL} (n/a: diverged or failed)", fontsize="medium")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_sweep(points: list[Point], results: dict, grid: dict[str, list[Any]], out: Path) -> list[Path]:
    """Every figure of a sweep into ``out``; returns their paths (none before any point finished)."""
    if not runs(results):
        return []
    paths = []
    for key in grid:
        path = out / f"median_rms_vs_{_file_name(key)}.png"
        plot_against_key(points, results, grid, key, path)
        paths.append(path)
    if len(grid) == 2:
        path = out / "median_rms_heatmap.png"
        plot_heatmap(points, results, grid, path)
        paths.append(path)
    return paths
