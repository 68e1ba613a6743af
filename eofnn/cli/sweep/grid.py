"""A sweep grid: dotted config keys mapped to lists of values, expanded into points with stable ids.

A grid file is YAML mapping dotted keys of a ``compare`` config to a list of values or to a logarithmic range::

    predictors.cl_eof.history_length: [2, 4, 8, 16]
    predictors.cl_eof.alpha: {log_range: [1.0e-12, 1.0e-6, 4]}   # 4 values, log-spaced, ends included

The points are the Cartesian product of the lists, first key slowest. A point's id is a readable slug of its
values plus a short hash of them, so it does not depend on the order of the keys or of the points.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from eofnn.errors import ConfigError, require

#: Most points a grid may expand to (each is a whole ``compare`` run), counted before anything is built.
MAX_POINTS = 10_000
#: Longest readable part of a point id (the hash keeps ids unique whatever is cut).
SLUG_CHARS = 80


@dataclass(frozen=True)
class GridPoint:
    """One point of a sweep: the swept values by dotted key, and its id (also its folder name)."""

    values: dict[str, Any]
    id: str


def log_range(start: float, stop: float, count: int) -> list[float]:
    """``count`` values from ``start`` to ``stop`` (both included), evenly spaced in log, 12 significant digits."""
    if count == 1:
        return [float(start)]
    ratio = stop / start
    return [float(f"{start * ratio ** (i / (count - 1)):.12g}") for i in range(count)]


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _values(key: str, spec: Any) -> list[Any]:
    """The list of values of one grid entry, checked."""
    if isinstance(spec, dict):
        require(set(spec) == {"log_range"},
                f"grid {key}={spec!r} is invalid: give a list of values or {{log_range: [start, stop, count]}}")
        bounds = spec["log_range"]
        require(isinstance(bounds, list) and len(bounds) == 3 and all(_is_number(b) for b in bounds),
                f"grid {key}: log_range={bounds!r} is invalid: it must be [start, stop, count] numbers")
        start, stop, count = bounds
        require(start > 0 and stop > 0,
                f"grid {key}: log_range={bounds!r} is invalid: start and stop must be > 0")
        require(isinstance(count, int) and count >= 1 and (count > 1 or start == stop),
                f"grid {key}: log_range={bounds!r} is invalid: count must be an integer >= 2 (1 only if start == stop)")
        require(count <= MAX_POINTS, f"grid {key}: log_range={bounds!r} is invalid: count={count} values, at most "
                f"{MAX_POINTS} (each is a compare run)")
        return log_range(start, stop, count)
    require(isinstance(spec, list),
            f"grid {key}={spec!r} is invalid: give a list of values or {{log_range: [start, stop, count]}}")
    require(len(spec) >= 1, f"grid {key}=[] is invalid: give at least one value")
    seen = set()
    for value in spec:
        text = json.dumps(value, sort_keys=True, default=str)
        require(text not in seen, f"grid {key} lists the value {value!r} twice")
        seen.add(text)
    return list(spec)


def parse_grid(raw: Any, source: str = "grid") -> dict[str, list[Any]]:
    """Check a grid mapping and expand its ranges: dotted key -> list of values."""
    require(isinstance(raw, dict) and len(raw) >= 1,
            f"{source} is invalid: it must map dotted config keys to lists, e.g. predictors.ol_eof.alpha: [1e-9, 1e-6]")
    grid = {}
    for key, spec in raw.items():
        require(isinstance(key, str) and re.fullmatch(r"[A-Za-z0-9_\-]+(\.[A-Za-z0-9_\-]+)*", key or "") is not None,
                f"grid key {key!r} is invalid: it must be a dotted config key such as predictors.ol_eof.alpha")
        grid[key] = _values(key, spec)
    for key in grid:
        for other in grid:
            require(not other.startswith(key + "."), f"grid keys {key!r} and {other!r} overlap: sweep one of them")
    n_points = math.prod(len(values) for values in grid.values())
    require(n_points <= MAX_POINTS, f"{source} has {n_points} points ("
            f"{' x '.join(str(len(v)) for v in grid.values())} values), more than the {MAX_POINTS} a sweep runs: "
            "sweep fewer keys or values, or split the grid")
    return grid


def load_grid(path: str | Path) -> dict[str, list[Any]]:
    """Read and check a grid YAML file."""
    path = Path(path)
    require(path.is_file(), f"grid={str(path)!r} is not a file")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"grid={str(path)!r} is not valid YAML: {str(err).splitlines()[0]}") from None
    return parse_grid(raw, f"grid {str(path)!r}")


def _short_names(keys: list[str]) -> dict[str, str]:
    """The shortest dotted suffix of each key that no other key ends with (``alpha``, ``cl_eof.alpha``)."""
    names = {}
    for key in keys:
        parts = key.split(".")
        for n in range(1, len(parts) + 1):
            suffix = ".".join(parts[-n:])
            if not any(other != key and (other == suffix or other.endswith("." + suffix)) for other in keys):
                break
        names[key] = suffix
    return names


def _slug_value(value: Any) -> str:
    if isinstance(value, float):
        text = f"{value:g}"
    elif isinstance(value, (str, int)):
        text = str(value)
    else:
        text = json.dumps(value, sort_keys=True, separators=(",", ":"))
    return re.sub(r"[^A-Za-z0-9.+\-]+", "-", text).strip("-") or "x"


def point_id(values: dict[str, Any], short_names: dict[str, str] | None = None) -> str:
    """Folder name of a point: ``<name>_<value>__...-<hash>``, keys sorted: the same whatever the grid's order."""
    digest = hashlib.sha1(json.dumps(values, sort_keys=True, default=str).encode()).hexdigest()[:10]
    short_names = short_names or _short_names(list(values))
    slug = "__".join(f"{short_names[k]}_{_slug_value(values[k])}" for k in sorted(values))
    return f"{slug[:SLUG_CHARS]}-{digest}"


def expand(grid: dict[str, list[Any]]) -> list[GridPoint]:
    """Every combination of the grid's values (first key slowest), each with its id."""
    keys = list(grid)
    names = _short_names(keys)
    points = []
    for combination in itertools.product(*(grid[k] for k in keys)):
        values = dict(zip(keys, combination, strict=True))
        points.append(GridPoint(values, point_id(values, names)))
    return points
