"""Config files are checked before jsonargparse reads them: text, YAML, and of a size that expands safely.

YAML aliases let a 1 kB file describe a billion nodes (the "billion laughs"); jsonargparse would expand them
while it validates, using hours and gigabytes. The node graph is composed (aliases stay shared) and its expanded
size counted with memoisation, so the check itself is cheap.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from eofnn.errors import ConfigError

#: eofnn's own configs (``configs/`` of the checkout eofnn runs from), where a config's ``scenario: realistic.yaml``
#: is looked for when no such file is beside the config.
INSTALLED_CONFIGS = Path(__file__).resolve().parents[2] / "configs"
#: Entries whose ``.yaml`` values are outputs or other files, not configs to load.
NOT_CONFIG_KEYS = ("out", "grid")
#: Most YAML nodes a config may expand to (the full study's config has about 300).
MAX_CONFIG_NODES = 100_000
#: Largest config file read, in bytes.
MAX_CONFIG_BYTES = 1_000_000


def _expanded_size(node: yaml.Node, memo: dict[int, int]) -> int:
    if id(node) in memo:
        return memo[id(node)]
    if isinstance(node, yaml.ScalarNode):
        size = 1
    elif isinstance(node, yaml.SequenceNode):
        size = 1 + sum(_expanded_size(child, memo) for child in node.value)
    else:
        size = 1 + sum(_expanded_size(k, memo) + _expanded_size(v, memo) for k, v in node.value)
    memo[id(node)] = size
    return size


def _scalars(node: yaml.Node, seen: set[int]):
    """Every scalar of the node graph; a tag that would build a Python object stops the walk with an error."""
    if id(node) in seen:
        return
    seen.add(id(node))
    if node.tag.startswith("tag:yaml.org,2002:python"):
        raise ConfigError(f"YAML tag !!{node.tag.removeprefix('tag:yaml.org,2002:')} is refused: a config cannot "
                          "build Python objects")
    if isinstance(node, yaml.ScalarNode):
        yield node.value
    elif isinstance(node, yaml.SequenceNode):
        for child in node.value:
            yield from _scalars(child, seen)
    elif isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            yield from _scalars(key, seen)
            yield from _scalars(value, seen)


def check_config_file(path: str | Path, _depth: int = 0) -> None:
    """One-line :class:`ConfigError` unless ``path`` is a readable YAML file of sane expanded size.

    YAML files it names (``scenario: reference.yaml``, relative to its folder) are checked the same way.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    if path.stat().st_size > MAX_CONFIG_BYTES:
        raise ConfigError(f"config file {str(path)!r} is larger than {MAX_CONFIG_BYTES} bytes: is it a config?")
    try:
        text = path.read_text(encoding="utf-8")
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except UnicodeDecodeError:
        raise ConfigError(f"config file {str(path)!r} is not text (UTF-8): is it a config?") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"config file {str(path)!r} is not valid YAML{where}: "
                          f"{getattr(err, 'problem', None) or type(err).__name__}") from None
    if node is None:
        return
    try:
        size = _expanded_size(node, {})
    except RecursionError:
        raise ConfigError(f"config file {str(path)!r} is nested too deeply") from None
    if size > MAX_CONFIG_NODES:
        raise ConfigError(f"config file {str(path)!r} expands to {size} YAML nodes (aliases included): at most "
                          f"{MAX_CONFIG_NODES} are allowed")
    for value in _scalars(node, set()):
        if _depth < 3 and isinstance(value, str) and value.endswith((".yaml", ".yml")) and "\n" not in value:
            nested = path.parent / value
            if nested.is_file():
                check_config_file(nested, _depth + 1)


def _is_config_name(value) -> bool:
    return isinstance(value, str) and value.endswith((".yaml", ".yml")) and "\n" not in value


def resolve_config_references(path: str | Path) -> str:
    """The ``--config`` value that loads ``path`` with its top-level ``.yaml`` entries found.

    A config names another (``scenario: realistic.yaml``) relative to its own folder; a config copied out of
    ``configs/`` still finds eofnn's own ``realistic.yaml``: each name is looked for beside the config first, then
    in :data:`INSTALLED_CONFIGS`. When every name is beside the config, that is ``path`` itself; otherwise the
    config's text with those names made absolute (jsonargparse reads a ``--config`` value as a path or as YAML).

    Raises
    ------
    ConfigError
        Naming the entry and every folder searched, when none holds the file.
    """
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return str(path)  # check_config_file says what is wrong with the file
    if not isinstance(raw, dict):
        return str(path)
    changed = False
    for key, value in raw.items():
        if key in NOT_CONFIG_KEYS or not _is_config_name(value) or Path(value).is_absolute():
            continue
        folders = [path.resolve().parent, INSTALLED_CONFIGS]
        found = next((folder / value for folder in folders if (folder / value).is_file()), None)
        if found is None:
            raise ConfigError(f"config file {str(path)!r}: {key}={value!r} is not a file in any folder searched: "
                              f"{folders[0]} (beside the config), {folders[1]} (eofnn's configs)")
        if found.parent != folders[0]:
            check_config_file(found)
            raw[key], changed = str(found), True
    return yaml.safe_dump(raw, sort_keys=False) if changed else str(path)
