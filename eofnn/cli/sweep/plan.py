"""From a base ``compare`` config and a grid to the resolved config of every point, checked before anything runs.

The base config is parsed by the ``compare`` parser itself (``eofnn.cli.commands.build_parser``) and dumped with every
default filled in, so a dotted grid key resolves exactly as ``eofnn compare`` would read it. Each point's config
is that dump with the swept values set; it is written to the point's folder and run with
``eofnn compare --config point.yaml``.

Checks: every grid key must name an existing config entry (its last part may be new only inside a free mapping
such as ``scenario.model_errors``, where the compare parser or the plant then checks the name), and every value of
every key is parsed, instantiated and planned as ``compare`` plans itself
(:func:`eofnn.evaluation.stages.plan_compare`: scenarios, ``train_in``, checkpoints, memory and time, and the
analyses' scenarios and grids) beside the first value of the other keys. Combinations that are only invalid together (say
``evaluation.frames`` below a swept ``evaluation.settle_frames``) are caught when that point starts, and recorded
as a failed point with compare's one-line error.
"""

from __future__ import annotations

import copy
import json
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from eofnn.cli.commands import COMMANDS, build_parser, one_line
from eofnn.cli.configfile import check_config_keys, resolve_config_references
from eofnn.cli.sweep.grid import GridPoint, expand
from eofnn.errors import CheckpointError, ConfigError, TelemetryError, require

#: Entries of a compare config that the sweep sets for each point itself.
RUN_KEYS = ("config", "out", "overwrite", "progress")


@dataclass(frozen=True)
class Point:
    """A point of a sweep: its id (folder name), swept values by dotted key, and its full resolved config (YAML)."""

    id: str
    values: dict[str, Any]
    config_yaml: str


def _compare_parser():
    return build_parser(["compare"])


def override_arguments(overrides: dict[str, Any]) -> list[str]:
    """``{"evaluation.frames": 1500}`` as compare's command line takes it: ``--evaluation.frames 1500`` (a string as
    it was typed; any other value as JSON, which compare's parser reads as YAML)."""
    arguments = []
    for key, value in overrides.items():
        arguments += [f"--{key}", value if isinstance(value, str) else json.dumps(value)]
    return arguments


def resolve_base(config_path: str | Path, overrides: dict[str, Any] | None = None) -> dict:
    """The base config as ``eofnn compare --config config_path --key value ...`` resolves it (``overrides``: dotted
    key -> value, applied after the file as compare applies its command line), defaults filled in.

    Raises
    ------
    ConfigError
        A misspelt key in the file (its line and the nearest allowed key), or an override compare refuses.
    """
    path = Path(config_path)
    require(path.is_file(), f"config={str(path)!r} is not a file")
    check_config_keys(path, COMMANDS["compare"].config)
    parser = _compare_parser()
    base_args = ["compare", "--config", resolve_config_references(path)]
    overrides = overrides or {}
    for key in overrides:
        require(key.split(".")[0] not in RUN_KEYS, f"--{key} is set by the sweep for each point: it cannot be "
                "overridden")
    from jsonargparse import ArgumentError

    try:
        cfg = parser.parse_args([*base_args, *override_arguments(overrides), "--out", "unused"])
    except ArgumentError as err:
        if not overrides:
            raise
        raise ConfigError(f"{one_line(err)} (with the sweep's overrides {' '.join(override_arguments(overrides))})"
                          ) from None
    resolved = yaml.safe_load(parser.dump(cfg))["compare"]
    for key in RUN_KEYS:
        resolved.pop(key, None)
    return resolved


def with_values(base: dict, values: dict[str, Any]) -> dict:
    """A copy of ``base`` with each dotted key set; every part but the last must already be a mapping there."""
    config = copy.deepcopy(base)
    for key, value in values.items():
        node, where = config, "the config"
        *parents, leaf = key.split(".")
        for part in parents:
            if part not in node:
                raise ConfigError(f"grid key {key!r} is unknown: {where} has no {part!r} (it has "
                                  f"{', '.join(map(str, node)) or 'nothing'})")
            if not isinstance(node[part], dict):
                raise ConfigError(f"grid key {key!r} is unknown: {where}.{part} is {node[part]!r}, not a mapping"
                                  .replace("the config.", ""))
            node, where = node[part], part if where == "the config" else f"{where}.{part}"
        node[leaf] = copy.deepcopy(value)
    return config


def to_yaml(config: dict) -> str:
    return yaml.safe_dump(config, sort_keys=False)


class _Checker:
    """Parses configs as ``eofnn compare`` does and plans them as it does (its stages' first), running nothing."""

    def __init__(self, workdir: Path) -> None:
        self.parser = _compare_parser()
        self.workdir = workdir

    def __call__(self, config: dict, label: str) -> None:
        from jsonargparse import ArgumentError

        from eofnn.evaluation.stages import plan_compare

        path = self.workdir / "point.yaml"
        path.write_text(to_yaml(config))
        try:
            cfg = self.parser.parse_args(["compare", "--config", str(path), "--out", str(self.workdir / "out")])
            init = self.parser.instantiate(cfg)["compare"]
            plan_compare(init.scenario, init.scenarios, init.predictors, init.evaluation, robustness=init.robustness,
                         simulated_margins=init.simulated_margins, pareto=init.pareto, log=lambda message: None,
                         trusted_networks=init.trusted_networks, allow_long=init.allow_long)
        except (ArgumentError, ConfigError, CheckpointError, TelemetryError, TypeError, ValueError) as err:
            # TypeError/ValueError: a value of the wrong type that reached a constructor unchecked.
            raise ConfigError(f"{label}: {one_line(err)}") from None


def plan(config_path: str | Path, grid: dict[str, list[Any]], overrides: dict[str, Any] | None = None) -> list[Point]:
    """Every point of ``grid`` over the base config with ``overrides`` (dotted key -> value, as
    :func:`resolve_base` applies them), checked (see the module's docstring).

    Raises
    ------
    ConfigError
        Also when a key is both overridden and swept (the grid would silently win).
    """
    for key in overrides or {}:
        for swept in grid:
            require(not (swept == key or swept.startswith(key + ".") or key.startswith(swept + ".")),
                    f"--{key} is also swept by the grid ({swept}): set it in one place")
    base = resolve_base(config_path, overrides)
    grid_points: list[GridPoint] = expand(grid)
    first = grid_points[0].values
    with tempfile.TemporaryDirectory(prefix="eofnn-sweep-") as tmp:
        check = _Checker(Path(tmp))
        check(with_values(base, first), "grid " + ", ".join(f"{k}={v!r}" for k, v in first.items()))
        for key, values in grid.items():
            for value in values[1:]:
                check(with_values(base, dict(first, **{key: value})), f"grid {key}={value!r}")
    return [Point(p.id, p.values, to_yaml(with_values(base, p.values))) for p in grid_points]
