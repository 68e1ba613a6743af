"""``sweep.csv``: one row per point, scenario and predictor, with the swept values and compare's metrics.

Points not run yet are one ``pending`` row, failed points one ``failed`` row with their error. The file is
rewritten atomically after every finished point, so it is always complete and consistent, and it holds no
timings: the same sweep gives the same file, byte for byte, whatever the backend or the order.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

from eofnn.cli.sweep.plan import Point
from eofnn.cli.sweep.point import write_atomic

CSV_FILE = "sweep.csv"
#: Columns before the swept keys and between them and the metrics.
ID_COLUMNS = ("point",)
RUN_COLUMNS = ("status", "scenario", "predictor")


def cell(value: Any) -> str:
    """A csv cell: floats exactly (shortest round-trip repr), lists and mappings as JSON, ``None`` empty."""
    if value is None:
        return ""
    if isinstance(value, (list, dict)):
        return json.dumps(value, sort_keys=True)
    return str(value)


def rows(points: list[Point], results: dict[str, dict]) -> tuple[list[str], list[dict[str, str]]]:
    """The columns and rows of ``sweep.csv`` for ``points`` and the results known so far (by point id)."""
    keys = list(points[0].values) if points else []
    metric_names: dict[str, None] = {}
    table = []
    for point in points:
        base = {"point": point.id, **{k: cell(v) for k, v in point.values.items()}}
        result = results.get(point.id)
        if result is None:
            table.append({**base, "status": "pending"})
        elif result["status"] != "done":
            table.append({**base, "status": "failed", "error": result.get("error") or ""})
        else:
            for scenario, predictors in result["scenarios"].items():
                for predictor, metrics in predictors.items():
                    metric_names.update(dict.fromkeys(metrics))
                    table.append({**base, "status": "done", "scenario": scenario, "predictor": predictor,
                                  **{name: cell(value) for name, value in metrics.items()}})
    return [*ID_COLUMNS, *keys, *RUN_COLUMNS, *metric_names, "error"], table


def write_csv(path: Path, points: list[Point], results: dict[str, dict]) -> None:
    """Rewrite ``sweep.csv`` atomically (a temporary file, then ``os.replace``)."""
    columns, table = rows(points, results)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, columns, restval="", lineterminator="\n")
    writer.writeheader()
    writer.writerows(table)
    write_atomic(path, buffer.getvalue())
