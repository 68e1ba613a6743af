"""``eofnn configs``: the example configs installed with eofnn (``eofnn/configs/``), listed or copied to edit.

They run by name from any folder (``eofnn compare --config realistic_sh``; :func:`eofnn.cli.configfile.
find_config_file`), a wheel's install included; ``copy`` gives a file of one's own, never replacing one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import yaml

from eofnn.cli.common import log
from eofnn.cli.configfile import bundled_config, bundled_configs
from eofnn.errors import ConfigError

DESCRIPTION = """\
eofnn's own configs, installed with it: list them, or copy one into a folder to edit it.

  eofnn configs list                           # each config's name and what it is
  eofnn configs copy realistic_small mine/     # mine/realistic_small.yaml; never replaces a file
  eofnn compare --config realistic_small --out results/realistic_small   # or run one by name, from any folder

A copied config that names another of eofnn's (scenario: realistic.yaml) finds it among eofnn's own while no such
file is beside it, and says so in one line; copy that one too to edit it."""


@dataclass(kw_only=True)
class ConfigsConfig:
    """``eofnn configs``: list eofnn's own configs or copy one.

    Parameters
    ----------
    action : str
        ``list`` (names and what each is) or ``copy`` (``NAME`` into ``FOLDER``).
    name : str, optional
        The config to copy, by name (``realistic_small``, with or without ``.yaml``).
    folder : str, optional
        Where to copy it (made if missing; default: the current folder).
    """

    action: str = "list"
    name: str | None = None
    folder: str | None = None


def add_arguments(parser) -> None:
    """``eofnn configs list`` and ``eofnn configs copy NAME [FOLDER]``: positional arguments."""
    parser.add_argument("action", choices=["list", "copy"], help="list eofnn's own configs, or copy one")
    parser.add_argument("name", nargs="?", default=None, help="copy: the config's name (see list)")
    parser.add_argument("folder", nargs="?", default=None, help="copy: the folder to copy it into; unset, the current one")


def describe(path: Path, width: int = 100) -> str:
    """What a config is: the first sentence of its leading comment, cut to ``width`` characters."""
    words = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        words += line.lstrip("#").split()
    text = " ".join(words)
    end = text.find(". ")
    text = text if end < 0 else text[:end + 1]
    return text if len(text) <= width else text[:width - 3].rsplit(" ", 1)[0] + " ..."


def list_configs() -> list[str]:
    """One line per config of eofnn's own: its name, padded, and what it is."""
    configs = bundled_configs()
    width = max(map(len, configs), default=0)
    return [f"{name:<{width}}  {describe(path)}" for name, path in configs.items()]


def copy_config(name: str | None, folder: str | Path | None = None) -> Path:
    """Copy eofnn's config ``name`` into ``folder`` (made if missing) as ``NAME.yaml``; returns the copy's path.

    Raises
    ------
    ConfigError
        When ``name`` is missing or not one of eofnn's configs, or the copy's path exists (a user's file is never
        replaced).
    """
    if not name:
        raise ConfigError("eofnn configs copy needs a NAME: one of " + ", ".join(bundled_configs()))
    source = bundled_config(name)
    if source is None:
        raise ConfigError(f"{name!r} is not one of eofnn's configs: " + ", ".join(bundled_configs()))
    folder = Path("." if folder is None else folder)
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"{str(folder)!r} is a file, not a folder to copy {source.name} into")
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / source.name
    try:
        with open(target, "x", encoding="utf-8") as copy:  # "x": never replaces a file, even one made meanwhile
            copy.write(source.read_text(encoding="utf-8"))
    except FileExistsError:
        raise ConfigError(f"{str(target)!r} exists: eofnn never replaces your file; move it or copy into another "
                          "folder") from None
    return target


def configs(cfg: ConfigsConfig, config_dump: str | None = None) -> Path | None:
    """List eofnn's configs on stdout, or copy one (said on stderr, with any config of eofnn's it names that the
    copy will find among eofnn's own); returns the copy's path."""
    if cfg.action == "list":
        if cfg.name is not None:
            raise ConfigError(f"eofnn configs list takes no NAME (got {cfg.name!r})")
        print("\n".join(list_configs()))
        return None
    if cfg.action != "copy":
        raise ConfigError(f"action={cfg.action!r}: allowed are list, copy")
    target = copy_config(cfg.name, cfg.folder)
    log(f"eofnn: copied {cfg.name!r} to {target}")
    raw = yaml.safe_load(target.read_text(encoding="utf-8"))
    for key, value in (raw.items() if isinstance(raw, dict) else ()):
        if isinstance(value, str) and bundled_config(value) is not None and not (target.parent / value).exists():
            log(f"eofnn: its {key} {value!r} is eofnn's own, found there while no {value} is beside the copy "
                f"(to edit it too: eofnn configs copy {Path(value).stem} {target.parent})")
    return target

