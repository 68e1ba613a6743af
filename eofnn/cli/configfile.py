"""Config files are checked before jsonargparse reads them: text, YAML, of a size that expands safely, and keys
that the command knows.

YAML aliases let a 1 kB file describe a billion nodes (the "billion laughs"); jsonargparse would expand them
while it validates, using hours and gigabytes. The node graph is composed (aliases stay shared) and its expanded
size counted with memoisation, so the check itself is cheap.

Every key is then checked against the command's configuration dataclasses, through the files a config names
(``scenario: realistic.yaml``): a misspelt key (``settle_frame:``) is one line that names the file, the key's line
in it and the nearest allowed key, where jsonargparse would name only a dotted option.
"""

from __future__ import annotations

import dataclasses
import difflib
import sys
import types
import typing
from pathlib import Path

import yaml

from eofnn.errors import ConfigError

#: eofnn's own configs, installed with the package (``eofnn/configs/``; a checkout's ``configs/`` links to it): a
#: config's ``scenario: realistic.yaml`` is looked for there when no such file is beside the config, and ``--config
#: NAME`` finds one by name (:func:`bundled_config`).
INSTALLED_CONFIGS = Path(__file__).resolve().parents[1] / "configs"
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
        hint = " (eofnn's own configs, run by name as --config NAME: eofnn configs list)" if not path.exists() else ""
        raise ConfigError(f"config file {str(path)!r} does not exist{hint}")
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


def bundled_configs() -> dict[str, Path]:
    """eofnn's own configs by name (``realistic_sh`` -> ``.../eofnn/configs/realistic_sh.yaml``), sorted."""
    return {path.stem: path for path in sorted(INSTALLED_CONFIGS.glob("*.yaml"))}


def bundled_config(name: str) -> Path | None:
    """The config of eofnn's own that ``name`` means (``realistic_sh`` or ``realistic_sh.yaml``); ``None`` if
    ``name`` is a path (it holds a folder separator) or names none of them."""
    if not name or "/" in name or "\\" in name:
        return None
    return bundled_configs().get(name.removesuffix(".yaml").removesuffix(".yml"))


def find_config_file(value: str, option: str = "--config", say=None) -> str:
    """The file that ``--config VALUE`` (or ``--scenario VALUE``) reads: ``value`` itself when it is a file, else
    the config of eofnn's own it names (:func:`bundled_config`: ``--config realistic_sh`` from any folder, a wheel's
    install included), said in one line to ``say`` (default: stderr), ``eofnn: --config 'realistic_sh' ->
    /abs/eofnn/configs/realistic_sh.yaml (eofnn's own; no such file here)``. Anything else is returned as it is,
    for :func:`check_config_file` to refuse.
    """
    found = bundled_config(value)
    if found is None or Path(value).exists():  # a name first: an inline YAML value may be too long for a path
        return value
    say = say or (lambda line: print(line, file=sys.stderr, flush=True))
    say(f"eofnn: {option} {value!r} -> {found} (eofnn's own; no such file here)")
    return str(found)


def _is_config_name(value) -> bool:
    return isinstance(value, str) and value.endswith((".yaml", ".yml")) and "\n" not in value


def find_config_reference(config_path: str | Path, key: str, value: str) -> Path:
    """The file that a top-level entry ``key: value`` of the config ``config_path`` names (``scenario:
    realistic.yaml``): ``value`` beside the config if it is there, else in :data:`INSTALLED_CONFIGS`.

    Raises
    ------
    ConfigError
        Naming the entry and every folder searched, when none holds the file.
    """
    if Path(value).is_absolute():
        return Path(value)
    config_path = Path(config_path)
    folders = [config_path.resolve().parent, INSTALLED_CONFIGS]
    found = next((folder / value for folder in folders if (folder / value).is_file()), None)
    if found is None:
        raise ConfigError(f"config file {str(config_path)!r}: {key}={value!r} is not a file in any folder searched: "
                          f"{folders[0]} (beside the config), {folders[1]} (eofnn's configs)")
    return found


def resolve_config_references(path: str | Path, say=None) -> str:
    """The ``--config`` value that loads ``path`` with its top-level ``.yaml`` entries found.

    A config names another (``scenario: realistic.yaml``) relative to its own folder; a config copied out of
    ``configs/`` still finds eofnn's own ``realistic.yaml``: each name is looked for beside the config first, then
    in :data:`INSTALLED_CONFIGS` (:func:`find_config_reference`). Every name found in eofnn's configs rather than
    beside the config is said in one line to ``say`` (default: stderr), ``eofnn: scenario 'realistic.yaml' ->
    /abs/configs/realistic.yaml (eofnn's own; none beside your config)``, since the file used is not the one a
    reader of the config would look for. When every name is beside the config, the value is ``path`` itself;
    otherwise the config's text with every name made absolute (jsonargparse reads a ``--config`` value as a path
    or as YAML).

    Raises
    ------
    ConfigError
        Naming the entry and every folder searched, when none holds the file.
    """
    path = Path(path)
    say = say or (lambda line: print(line, file=sys.stderr, flush=True))
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return str(path)  # check_config_file says what is wrong with the file
    if not isinstance(raw, dict):
        return str(path)
    beside = path.resolve().parent
    found_names: dict[str, Path] = {}
    for key, value in raw.items():
        if key in NOT_CONFIG_KEYS or not _is_config_name(value) or Path(value).is_absolute():
            continue
        found_names[key] = find_config_reference(path, key, value)
    elsewhere = {key: found for key, found in found_names.items() if found.parent != beside}
    for key, found in elsewhere.items():
        check_config_file(found)
        say(f"eofnn: {key} {raw[key]!r} -> {found} (eofnn's own; none beside your config {str(path)!r})")
    if not elsewhere:
        return str(path)
    for key, found in found_names.items():  # the text is read from no folder: every name absolute
        raw[key] = str(found)
    return yaml.safe_dump(raw, sort_keys=False)


# --- keys against the command's configuration -------------------------------------------------------------------

def unwrap_optional(hint):
    """``X`` for ``X | None`` (and ``Optional[X]``); ``hint`` itself otherwise."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        members = [a for a in typing.get_args(hint) if a is not type(None)]
        dataclass_members = [a for a in members if _is_config_class(a)]
        if len(members) == 1:
            return members[0]
        if len(dataclass_members) == 1:  # ``Scenario | str``: a mapping is read as the dataclass
            return dataclass_members[0]
    return hint


def _only_config_classes(hint) -> bool:
    """Whether ``hint`` admits config dataclasses only (``X``, ``X | None``): no scalar but a file name is one."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return all(_is_config_class(a) for a in typing.get_args(hint) if a is not type(None))
    return _is_config_class(hint)


def _is_config_class(hint) -> bool:
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def config_field_types(cls: type) -> dict[str, typing.Any] | None:
    """The settable fields of a config dataclass and their types; ``None`` if the types cannot be resolved (its keys
    are then left to jsonargparse)."""
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # an annotation that names something unimportable here: not this check's business
        return None
    return {f.name: hints.get(f.name, typing.Any) for f in dataclasses.fields(cls) if f.init
            and not f.name.startswith("_")}


def unknown_key_message(path: str | Path, line: int, key: str, where: str, allowed: list[str]) -> str:
    """``config file 'x.yaml', line 9: unknown key 'settle_frame' in evaluation: did you mean 'settle_frames'?``
    (``line`` counts from 1); with the allowed keys listed when none is close."""
    place = f"in {where}" if where else "at the top level"
    close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}?" if close else f"allowed are {', '.join(sorted(allowed))}"
    return f"config file {str(path)!r}, line {line}: unknown key {key!r} {place}: {hint}"


class _KeyChecker:
    """Walks a composed YAML node graph beside a config dataclass and refuses the first key that is not a field.

    Only what is certain is checked: mappings read as a config dataclass (directly, as ``X | None``, as items of a
    ``list[X]`` or values of a ``dict[str, X]``), the files such a mapping is given as (``scenario:
    realistic.yaml``), and the values of a free mapping that a dataclass declares as changes of another
    (``_mapping_value_keys = {"scenarios": Plant}``: each scenario's keys are the plant's fields). Other free
    mappings (``network``, ``search``) are left to the checks of the floors that read them.
    """

    def __init__(self) -> None:
        self.seen: set[tuple[int, type]] = set()

    def mapping(self, node: yaml.MappingNode, cls: type, path: Path, where: str, depth: int) -> None:
        if (id(node), cls) in self.seen:  # an alias: its nodes are checked once
            return
        self.seen.add((id(node), cls))
        hints = config_field_types(cls)
        if hints is None:
            return
        for key_node, value_node in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # ``<<: *defaults``: the merged mappings are this one's
                merged = value_node.value if isinstance(value_node, yaml.SequenceNode) else [value_node]
                for item in merged:
                    if isinstance(item, yaml.MappingNode):
                        self.mapping(item, cls, path, where, depth)
                continue
            if not isinstance(key_node, yaml.ScalarNode):
                continue
            key = key_node.value
            if key not in hints:
                raise ConfigError(unknown_key_message(path, key_node.start_mark.line + 1, key, where, list(hints)))
            child_where = f"{where}.{key}" if where else key
            free_values = getattr(cls, "_mapping_value_keys", {}).get(key)
            if free_values is not None and isinstance(value_node, yaml.MappingNode):
                # A free mapping whose values are changes of a dataclass (``scenarios: {name: {dm_gain: 2.0}}``).
                for name_node, changes in value_node.value:
                    if isinstance(name_node, yaml.ScalarNode) and isinstance(changes, yaml.MappingNode):
                        self.mapping(changes, free_values, path, f"{child_where}.{name_node.value}", depth)
                continue
            self.value(value_node, hints[key], path, child_where, depth,
                       top_level_key=key if depth == 0 and not where else None)

    def value(self, node: yaml.Node, hint, path: Path, where: str, depth: int, top_level_key: str | None) -> None:
        only_mappings = _only_config_classes(hint)
        hint = unwrap_optional(hint)
        if _is_config_class(hint):
            if isinstance(node, yaml.MappingNode):
                self.mapping(node, hint, path, where, depth)
            elif isinstance(node, yaml.ScalarNode) and _is_config_name(node.value) and depth < 3:
                self.file(node.value, hint, path, where, depth, top_level_key)
            elif only_mappings and not (isinstance(node, yaml.ScalarNode) and node.tag == "tag:yaml.org,2002:null"):
                # ``sensor: 5``: a value that can only be a mapping of the dataclass's fields (or a file of one).
                shown = node.value if isinstance(node, yaml.ScalarNode) else "a list"
                raise ConfigError(f"config file {str(path)!r}, line {node.start_mark.line + 1}: {where}={shown} is "
                                  f"invalid: it must be a mapping of {hint.__name__} fields (or a .yaml file of one)")
            return
        origin, args = typing.get_origin(hint), typing.get_args(hint)
        if origin in (list, tuple) and args and isinstance(node, yaml.SequenceNode):
            item = unwrap_optional(args[0])
            if _is_config_class(item):
                for child in node.value:
                    if isinstance(child, yaml.MappingNode):
                        self.mapping(child, item, path, where, depth)
        elif origin is dict and len(args) == 2 and isinstance(node, yaml.MappingNode):
            item = unwrap_optional(args[1])
            if _is_config_class(item):
                for key_node, child in node.value:
                    if isinstance(key_node, yaml.ScalarNode) and isinstance(child, yaml.MappingNode):
                        self.mapping(child, item, path, f"{where}.{key_node.value}", depth)

    def file(self, name: str, cls: type, path: Path, where: str, depth: int, top_level_key: str | None) -> None:
        """A mapping given as a file: beside ``path`` (or, for a top-level entry, in eofnn's configs)."""
        if top_level_key is not None:
            try:
                nested = find_config_reference(path, top_level_key, name)
            except ConfigError:
                return  # resolve_config_references says so, naming the folders searched
        else:
            nested = path.parent / name
        if nested.is_file():
            self.document(nested, cls, where, depth + 1)

    def document(self, path: Path, cls: type, where: str, depth: int) -> None:
        try:
            node = yaml.compose(path.read_text(encoding="utf-8"), Loader=yaml.SafeLoader)
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            return  # check_config_file says what is wrong with the file
        if isinstance(node, yaml.MappingNode):
            self.mapping(node, cls, path, where, depth)


def check_config_keys(path: str | Path, config_class: type, where: str = "") -> None:
    """One-line :class:`ConfigError` for the first key of the YAML file ``path``, or of a file it names, that is not
    a field of ``config_class`` (a command's configuration dataclass) at its level: the file, the key's line in it
    and the nearest allowed key (:func:`unknown_key_message`).

    ``where`` is the dotted key the file is read at (``scenario`` for ``--scenario FILE``); the default, the whole
    configuration of a command (``--config FILE``, whose ``config:`` entry is the parser's own). Run it after
    :func:`check_config_file`, which refuses what is not safe to compose.
    """
    checker = _KeyChecker()
    path = Path(path)
    try:
        node = yaml.compose(path.read_text(encoding="utf-8"), Loader=yaml.SafeLoader)
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return
    if not isinstance(node, yaml.MappingNode):
        return
    if not where:  # ``config:`` in a --config file names another config: jsonargparse reads it
        node = yaml.MappingNode(node.tag, [(k, v) for k, v in node.value
                                           if not (isinstance(k, yaml.ScalarNode) and k.value == "config")])
    checker.mapping(node, config_class, path, where, 0)
