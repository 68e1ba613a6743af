"""The table of ``eofnn``'s subcommands and the parsing of a command line into the configuration of one.

Every value of a config can be overridden on the command line with its dotted key, e.g.
``--predictors.cl_eof.history_length 8`` or ``--scenario.atmosphere.r0_m 0.1``. Networks are named by
``class_path`` (any ``torch.nn.Module`` importable from Python; the folder of ``--config`` is on the path while the
config is read) and ``init_args``. :func:`parse` is what :func:`eofnn.cli.main.main` and a sweep's points share:
command-line arguments in, the command's instantiated configuration and its resolved YAML out.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import difflib
import importlib
import re
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import yaml
from jsonargparse import ActionConfigFile, ArgumentParser, DefaultHelpFormatter
from jsonargparse import ArgumentError as JsonArgError

from eofnn import __version__
from eofnn.cli.configfile import (
    check_config_file,
    check_config_keys,
    config_field_types,
    find_config_file,
    resolve_config_references,
    unwrap_optional,
)
from eofnn.errors import CheckpointError, ConfigError, DivergedError, OutputError, TelemetryError

DESCRIPTION = """\
eofnn: predictive wavefront control for adaptive optics, in simulated closed loop.

  eofnn compare  --config configs/paper_small.yaml --out results/small   # scenarios x controllers, one command
  eofnn fit      --scenario configs/reference.yaml --predictor.history closed_loop --out runs/cl.ckpt
  eofnn evaluate --config configs/evaluate.yaml --out results/eval          # saved checkpoints under any plant
  eofnn simulate --scenario configs/reference.yaml --out runs/integrator.fits  # one controller -> telemetry
  eofnn stability --checkpoint runs/cl.ckpt --scenario configs/reference.yaml --out results/stab  # margins
  eofnn sweep    --config configs/paper_small.yaml --grid GRID.yaml --out results/sweep  # a grid of compares
  eofnn identify --telemetry run.fits --out plant.json                     # plant from dithered telemetry
  eofnn fit      --telemetry run.fits --plant plant.json --out runs/ol.ckpt  # train on telemetry alone
  eofnn replay   --checkpoint runs/ol.ckpt --telemetry held_out.fits --out results/replay
  eofnn export   --checkpoint runs/ol.ckpt --out filter.fits                # for eofnn.runtime / any RTC
  eofnn twin     --telemetry run.fits --out twin/         # twin.yaml + identified.json from telemetry alone
  eofnn configs  list                                                      # eofnn's own configs; copy NAME DIR

Each subcommand takes --config FILE (YAML) and dotted overrides; '<subcommand> --help' lists them all,
'<subcommand> --print_config' prints the resolved configuration.
"""

USER_ERRORS = (ConfigError, CheckpointError, TelemetryError, DivergedError, OutputError, JsonArgError)


@dataclass(frozen=True)
class Command:
    """One subcommand: its one-line help, and where its description, configuration and function live.

    The subcommand is the function ``module.function(cfg, config_dump)``; its parser is built from the dataclass
    ``module.config`` (fields, types and numpydoc), so a command called from Python and from the command line take
    the same typed configuration. The module is imported only when the subcommand is used, so ``eofnn --help`` and
    ``eofnn --version`` answer without torch, Lightning or HCIPy (seconds of imports), and ``eofnn sweep --help``
    without the others'.
    """

    help: str
    module: str
    description_name: str
    config_name: str
    function_name: str
    #: A function of ``module``, ``(parser) -> None``, that adds the command's arguments itself (positional ones:
    #: ``eofnn configs copy NAME FOLDER``); unset, the configuration's fields are the options, with ``--config FILE``.
    arguments_name: str | None = None

    def _get(self, name: str):
        return getattr(importlib.import_module(self.module), name)

    @property
    def description(self) -> str:
        return self._get(self.description_name)

    @property
    def config(self) -> type:
        """The command's configuration dataclass."""
        return self._get(self.config_name)

    @property
    def run(self) -> Callable[..., object]:
        """The command's function, ``(cfg, config_dump) -> result``."""
        return self._get(self.function_name)

    def add_arguments(self, parser: ArgumentParser) -> None:
        """The configuration's fields as the parser's options (and ``--config FILE`` unless it has a field of that
        name)."""
        if self.arguments_name is not None:
            self._get(self.arguments_name)(parser)
            return
        names = {f.name for f in fields(self.config)}
        if "config" not in names:
            parser.add_argument("--config", action=ActionConfigFile, help="YAML configuration file.")
        parser.add_class_arguments(self.config, nested_key=None, as_group=False)

    @property
    def takes_config_files(self) -> bool:
        """Whether the command reads config files (``--config FILE`` and config groups given as files)."""
        return self.arguments_name is None

    def build(self, parsed) -> Any:
        """The configuration dataclass from the instantiated namespace of its options."""
        return self.config(**{f.name: parsed[f.name] for f in fields(self.config)})


COMMANDS: dict[str, Command] = {
    "compare": Command("Scenarios x controllers: train, evaluate, report.", "eofnn.cli.compare", "COMPARE",
                       "CompareConfig", "compare"),
    "fit": Command("Train one predictor and write a checkpoint.", "eofnn.cli.fit", "DESCRIPTION", "FitConfig", "fit"),
    "evaluate": Command("Run saved checkpoints under any plant.", "eofnn.cli.compare", "EVALUATE", "EvaluateConfig",
                        "evaluate"),
    "simulate": Command("Simulate one controller and save telemetry.", "eofnn.cli.simulate", "DESCRIPTION",
                        "SimulateConfig", "simulate"),
    "stability": Command("Stability margins of a linear predictor in a plant.", "eofnn.cli.stability", "DESCRIPTION",
                         "StabilityConfig", "stability"),
    "sweep": Command("A grid of compare runs: resumable, local or on Ray.", "eofnn.cli.sweep", "DESCRIPTION",
                     "SweepConfig", "sweep"),
    "identify": Command("Identify the plant from dithered telemetry.", "eofnn.cli.telemetry", "IDENTIFY",
                        "IdentifyConfig", "identify"),
    "replay": Command("Replay a checkpoint on held-out telemetry.", "eofnn.cli.telemetry", "REPLAY", "ReplayConfig",
                      "replay"),
    "export": Command("Export a linear predictor as filter FITS.", "eofnn.cli.telemetry", "EXPORT", "ExportConfig",
                      "export"),
    "twin": Command("Identify a twin of the system from its telemetry alone.", "eofnn.cli.twin", "DESCRIPTION",
                    "TwinConfig", "twin"),
    "configs": Command("List eofnn's own configs, or copy one to edit.", "eofnn.cli.configs", "DESCRIPTION",
                       "ConfigsConfig", "configs", arguments_name="add_arguments"),
}


_ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|obj|exc|ref):`~?([^`]+)`")
_LITERAL = re.compile(r"``([^`]+)``")


def plain_text(text: str) -> str:
    """Help text without Sphinx markup: ``:class:`~a.b.C``` -> ``C``, ````x```` -> ``x``."""
    def role(match: re.Match) -> str:
        target = match.group(1)
        return target.rsplit(".", 1)[-1] if match.group(0).split("`")[1].startswith("~") else target

    return _LITERAL.sub(r"\1", _ROLE.sub(role, text))


class _HelpFormatter(DefaultHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Keeps the examples in the descriptions laid out as written; help texts taken from docstrings lose their
    Sphinx markup (``:class:``, double back-ticks), which a terminal shows raw."""

    def _expand_help(self, action) -> str:
        return plain_text(super()._expand_help(action))

    def _format_text(self, text: str) -> str:
        return super()._format_text(plain_text(text))

    def start_section(self, heading) -> None:
        super().start_section(plain_text(heading) if heading else heading)


def build_parser(commands: Iterable[str] | None = None) -> ArgumentParser:
    """The ``eofnn`` parser; only the subcommands in ``commands`` (default: all) get their arguments (and import
    their modules): the others are listed with their one-line help, enough for ``eofnn --help``."""
    full = set(COMMANDS if commands is None else commands)
    # allow_abbrev=False: an option is its whole name (argparse would take --evaluation.frame for
    # --evaluation.frames, and a typo for another option); the subcommands' parsers inherit it.
    parser = ArgumentParser(prog="eofnn", description=DESCRIPTION, exit_on_error=False, formatter_class=_HelpFormatter,
                            allow_abbrev=False)
    parser.add_argument("--version", action="version", version=f"eofnn {__version__}", help="Print the version and exit.")
    sub = parser.add_subcommands(dest="command")
    for name, command in COMMANDS.items():
        if name in full:
            child = ArgumentParser(description=command.description, exit_on_error=False,
                                   formatter_class=_HelpFormatter)
            command.add_arguments(child)
        else:
            child = ArgumentParser(description=command.help, exit_on_error=False, formatter_class=_HelpFormatter)
        sub.add_subcommand(name, child, help=command.help)
    return parser


_NOISE = ("Problem with given class_path",)
_UNION = "Does not validate against any of the Union subtypes"
_UNION_NOISE = (_UNION, "Subtypes:", "Errors:", "Given value type:", "Expected a <class 'NoneType'>")


def _user_error(err: BaseException) -> BaseException | None:
    """The error of eofnn's own checks behind an error jsonargparse raised while instantiating, if any."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, USER_ERRORS):
            return err
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return None


def one_line(err: BaseException) -> str:
    """Collapse jsonargparse's nested messages into one line, each message once."""
    lines = [line.strip().removeprefix("- ") for line in str(err).splitlines() if line.strip()]
    lines = [line for line in lines if not line.startswith(_NOISE)]
    if any(line.strip().startswith(_UNION) for line in str(err).splitlines()):
        # An optional nested config (X | None): the reason it is not an X is the message, not the union's listing.
        lines = [line for line in lines if not line.startswith(_UNION_NOISE)]
    kept: list[str] = []
    for line in lines:  # jsonargparse repeats a nested error at each level: keep its first statement
        plain = line.replace('"', "'").replace('Parser key ', "")
        if not any(plain.split(": ", 1)[-1] in seen.replace('"', "'") for seen in kept):
            kept.append(line)
    return ": ".join(kept).replace('Parser key "', "").replace('":', ":").replace("::", ":")


def _nested_files(args: list[str], config_class: type) -> list[tuple[str, type, str]]:
    """``(field, dataclass, file)`` for each option of the command line that gives a config group as a YAML file
    (``--scenario configs/realistic.yaml``), so that its keys are checked as a ``--config`` file's are."""
    hints = config_field_types(config_class) or {}
    found = []
    for index, arg in enumerate(args):
        if not arg.startswith("--"):
            continue
        name, _, value = arg[2:].partition("=")
        if not value and index + 1 < len(args):
            value = args[index + 1]
        group = unwrap_optional(hints.get(name))
        if dataclasses.is_dataclass(group) and value.endswith((".yaml", ".yml")) and Path(value).is_file():
            found.append((name, group, value))
    return found


def _prepare_config_files(args: list[str], folders: list[str]) -> list[str]:
    """Check every ``--config`` file before jsonargparse reads it (its keys too, and those of the files it names:
    :func:`~eofnn.cli.configfile.check_config_keys`), and add its folder to ``folders`` (put on the Python path
    while the command runs, so a user's module beside their config (``class_path: my_net.Net``) imports without
    PYTHONPATH tricks). A config group given as a file on the command line (``--scenario FILE``) has its keys
    checked the same way.

    Returns ``args`` with eofnn's own configs found: by name (``--config realistic_sh``, ``--scenario realistic``:
    :func:`~eofnn.cli.configfile.find_config_file`) and as the references of a config (``scenario:
    realistic.yaml`` in a config copied out of ``configs/``: :func:`~eofnn.cli.configfile.resolve_config_references`).
    """
    command = COMMANDS.get(args[0]) if args else None
    hints = (config_field_types(command.config) or {}) if command is not None and command.takes_config_files else {}
    args = list(args)
    for index, value in enumerate(args):  # a bare name of eofnn's own configs: --config realistic_sh
        option = args[index - 1] if index > 0 else ""
        if option == "--config" or (option.startswith("--") and dataclasses.is_dataclass(
                unwrap_optional(hints.get(option[2:])))):
            args[index] = find_config_file(value, option)
    resolved = list(args)
    for index, value in enumerate(args):
        if index > 0 and args[index - 1] == "--config":
            check_config_file(value)
            folders.append(str(Path(value).resolve().parent))
            if args[0] != "sweep":  # sweep's --config is the base of a compare, resolved by the sweep
                if command is not None:
                    check_config_keys(value, command.config)
                resolved[index] = resolve_config_references(value)
    if command is not None and args[0] != "sweep" and command.takes_config_files:
        for name, group, path in _nested_files(args, command.config):
            check_config_file(path)
            check_config_keys(path, group, where=name)
    return resolved


def split_sweep_overrides(args: list[str]) -> tuple[list[str], dict[str, str]]:
    """``eofnn sweep``'s command line without its dotted options, and those options as the overrides of its base
    config: ``--evaluation.frames 1500`` (or ``--evaluation.frames=1500``) -> ``{"evaluation.frames": "1500"}``,
    the value as typed (compare's parser reads it, as ``eofnn compare --evaluation.frames 1500`` would).

    Raises
    ------
    ConfigError
        For a dotted option without a value.
    """
    own = {f.name for f in fields(COMMANDS["sweep"].config)}
    kept: list[str] = []
    overrides: dict[str, str] = {}
    index = 0
    while index < len(args):
        arg = args[index]
        name, equals, value = arg[2:].partition("=") if arg.startswith("--") else ("", "", "")
        if "." in name and name.split(".")[0] not in own:
            if not equals:
                if index + 1 >= len(args) or args[index + 1].startswith("--"):
                    raise ConfigError(f"--{name} has no value: give one, e.g. --{name} VALUE")
                index += 1
                value = args[index]
            overrides[name] = value
        else:
            kept.append(arg)
        index += 1
    return kept, overrides


@contextlib.contextmanager
def _on_python_path(folders: list[str]):
    """``folders`` first on ``sys.path`` while the command runs, and the path as it was afterwards."""
    before = list(sys.path)
    sys.path[:0] = [f for f in dict.fromkeys(folders) if f not in sys.path]
    try:
        yield
    finally:
        sys.path[:] = before



_UNRECOGNIZED = "unrecognized arguments:"


def _nearest_options(parser: ArgumentParser, command: str, message: str) -> str:
    """``did you mean --x?`` for each option of ``message`` (argparse's "unrecognized arguments: ...") that is close
    to one of ``command``'s options (abbreviations are refused: ``--evaluation.frame`` is not
    ``--evaluation.frames``); empty when the message is another one or nothing is close."""
    if _UNRECOGNIZED not in message:
        return ""
    subcommands = getattr(parser, "_subcommands_action", None)
    child = None if subcommands is None else subcommands._name_parser_map.get(command)
    known = [option for action in (child or parser)._actions for option in action.option_strings
             if option.startswith("--")]
    given = [word.split("=", 1)[0] for word in message.split(_UNRECOGNIZED, 1)[1].split() if word.startswith("--")]
    hints = []
    for option in dict.fromkeys(given):
        near = difflib.get_close_matches(option, known, n=1, cutoff=0.75)
        if near:
            hints.append(f"{option}: did you mean {near[0]}?")
    return "; ".join(hints)


@dataclass(frozen=True)
class Parsed:
    """A parsed command line: the subcommand, its instantiated configuration and its resolved YAML (``config.yaml``
    of its outputs)."""

    command: str
    config: Any
    dump: str
    #: The folders of the ``--config`` files, on ``sys.path`` while the command runs (a user's module beside their
    #: config); the path is as it was afterwards.
    folders: tuple[str, ...] = ()

    def run(self) -> object:
        """Run the subcommand on its configuration."""
        with _on_python_path(list(self.folders)):
            return COMMANDS[self.command].run(self.config, self.dump)


def parse(args: list[str]) -> Parsed:
    """Parse ``args`` (the command line after ``eofnn``) into a :class:`Parsed`; ``--help`` and
    ``--print_config`` exit as argparse does.

    Raises
    ------
    ConfigError, CheckpointError, TelemetryError, jsonargparse.ArgumentError
        For values that cannot mean what they say (one line each through :func:`one_line`).
    """
    # Only the subcommand asked for is built (and imported: seconds); ``eofnn --help`` lists them all without.
    parser = build_parser([args[0]] if args and args[0] in COMMANDS else [])
    folders: list[str] = []
    args = _prepare_config_files(args, folders)
    overrides: dict[str, str] = {}
    if args and args[0] == "sweep":  # dotted options are the base config's, set at every point
        args, overrides = split_sweep_overrides(args)
    with _on_python_path(folders):
        try:
            cfg = parser.parse_args(args)
        except JsonArgError as err:
            hint = _nearest_options(parser, args[0] if args else "", str(err))
            if not hint:
                raise
            raise ConfigError(f"{one_line(err)} ({hint})") from None
        command = cfg.command
        dump = yaml.safe_load(parser.dump(cfg))[command]
        sub_dump = yaml.safe_dump({k: v for k, v in dump.items() if k != "config"}, sort_keys=False)
        try:
            init = COMMANDS[command].build(parser.instantiate(cfg)[command])
        except (ValueError, TypeError) as err:  # a nested config's own check, wrapped by jsonargparse
            cause = _user_error(err)
            if cause is None:
                raise
            raise cause from None
    if overrides:
        init = dataclasses.replace(init, overrides={**init.overrides, **overrides})
    return Parsed(command, init, sub_dump, tuple(folders))
