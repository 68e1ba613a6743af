"""The ``eofnn`` command line: a table of subcommands, each configured by YAML and dotted overrides (jsonargparse).

Every value of a config can be overridden on the command line with its dotted key, e.g.
``--predictors.cl_eof.history_length 8`` or ``--scenario.atmosphere.r0_m 0.1``. Networks are named by
``class_path`` (any ``torch.nn.Module`` importable from Python; the folder of ``--config`` is on the path) and
``init_args``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import yaml
from jsonargparse import ArgumentError as JsonArgError
from jsonargparse import ArgumentParser, DefaultHelpFormatter

from eofnn.cli import compare, fit, simulate
from eofnn.errors import CheckpointError, ConfigError, DivergedError, TelemetryError

DESCRIPTION = """\
eofnn: predictive wavefront control for adaptive optics, in simulated closed loop.

  eofnn compare  --config configs/paper_small.yaml --out results/small   # scenarios x controllers, one command
  eofnn fit      --scenario configs/reference.yaml --predictor.history closed_loop --out runs/cl.ckpt
  eofnn evaluate --config configs/evaluate.yaml --out results/eval          # saved checkpoints under any plant
  eofnn simulate --scenario configs/reference.yaml --out runs/integrator.fits  # one controller -> telemetry

Each subcommand takes --config FILE (YAML) and dotted overrides; '<subcommand> --help' lists them all,
'<subcommand> --print_config' prints the resolved configuration.
"""

USER_ERRORS = (ConfigError, CheckpointError, TelemetryError, DivergedError, JsonArgError)


@dataclass(frozen=True)
class Command:
    """One subcommand: its one-line help, its description, how it adds its arguments and how it runs."""

    help: str
    description: str
    add_arguments: Callable[[ArgumentParser], None]
    run: Callable[..., object]


COMMANDS: dict[str, Command] = {
    "compare": Command("Scenarios x controllers: train, evaluate, report.", compare.COMPARE,
                       compare.add_compare_arguments, compare.run_compare),
    "fit": Command("Train one predictor and write a checkpoint.", fit.DESCRIPTION, fit.add_arguments, fit.run),
    "evaluate": Command("Run saved checkpoints under any plant.", compare.EVALUATE, compare.add_evaluate_arguments,
                        compare.run_evaluate),
    "simulate": Command("Simulate one controller and save telemetry.", simulate.DESCRIPTION, simulate.add_arguments,
                        simulate.run),
}


class _HelpFormatter(DefaultHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Keeps the examples in the descriptions laid out as written."""


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="eofnn", description=DESCRIPTION, exit_on_error=False, formatter_class=_HelpFormatter)
    sub = parser.add_subcommands(dest="command")
    for name, command in COMMANDS.items():
        child = ArgumentParser(description=command.description, exit_on_error=False)
        command.add_arguments(child)
        sub.add_subcommand(name, child, help=command.help)
    return parser


def _one_line(err: BaseException) -> str:
    """Collapse jsonargparse's nested messages into one line."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    lines = [line for line in lines if not line.startswith("Problem with given class_path")]
    return ": ".join(lines).replace('Parser key "', "").replace('":', ":")


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings reach a user of the command line as one line each, without a source line."""
    print(f"eofnn: warning: {message}", file=sys.stderr)


def _config_folders_on_path(args: list[str]) -> None:
    """A user's module beside their config (``class_path: my_net.Net``) imports without PYTHONPATH tricks."""
    for flag, value in zip(args, args[1:], strict=False):
        if flag == "--config":
            folder = str(Path(value).resolve().parent)
            if folder not in sys.path:
                sys.path.insert(0, folder)


def main(args: list[str] | None = None) -> int:
    """Entry point of the ``eofnn`` console script; returns the exit status (2 bad input, 130 interrupted)."""
    args = list(sys.argv[1:] if args is None else args)
    _config_folders_on_path(args)
    # Lightning announces the accelerators of every Trainer at INFO: the command line keeps to warnings.
    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)
    parser = build_parser()
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            # Lightning's hint that simulated streams could use more DataLoader workers does not apply to them.
            warnings.filterwarnings("ignore", message=".*does not have many workers.*")
            # Lightning's own call of a deprecated torch pytree API: nothing a user can act on.
            warnings.filterwarnings("ignore", message=".*isinstance\\(treespec, LeafSpec\\)` is deprecated.*")
            cfg = parser.parse_args(args)
            command = cfg.command
            dump = yaml.safe_load(parser.dump(cfg))[command]
            sub_dump = yaml.safe_dump({k: v for k, v in dump.items() if k != "config"}, sort_keys=False)
            COMMANDS[command].run(parser.instantiate(cfg)[command], sub_dump)
    except USER_ERRORS as err:
        print(f"eofnn: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("eofnn: interrupted: nothing was written (earlier results are untouched)", file=sys.stderr)
        return 130
    return 0


def console() -> None:
    """Console-script wrapper: exit with :func:`main`'s status."""
    sys.exit(main())


if __name__ == "__main__":
    console()
