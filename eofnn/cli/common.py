"""Arguments and helpers shared by the subcommands."""

from __future__ import annotations

import sys
from typing import Any

from jsonargparse import ActionConfigFile, ArgumentParser

from eofnn.evaluation.config import EvaluationConfig
from eofnn.sim.plant import Plant
from eofnn.sim.scenario import Scenario


def log(message: str) -> None:
    """Progress lines go to stderr, so that stdout stays clean for what a command prints as its result."""
    print(message, file=sys.stderr, flush=True)


def add_common(parser: ArgumentParser, out_help: str) -> None:
    parser.add_argument("--config", action=ActionConfigFile, help="YAML configuration file.")
    parser.add_argument("--scenario", type=Scenario, default=Scenario(),
                        help="Telescope (grid), atmosphere, frame rate and plant (delay and model errors).")
    parser.add_argument("--out", type=str, required=True, help=out_help)
    parser.add_argument("--overwrite", type=bool, default=False, help="Replace existing output.")
    parser.add_argument("--progress", type=bool | None, default=None,
                        help="Progress bars (default: only when stderr is a terminal).")
    parser.add_argument("--trusted_networks", type=list[str], default=[],
                        help="Network class paths, beyond eofnn's own, that checkpoints may name (importing a "
                             "module runs its code: name only modules you trust).")


def add_evaluation(parser: ArgumentParser) -> None:
    names = ", ".join(Plant.model_error_names())
    parser.add_argument("--scenarios", type=dict[str, dict[str, Any]], default={"nominal": {}},
                        help=f"Scenario name -> plant changes, e.g. {{nominal: {{}}, dm_gain_2: {{dm_gain: 2.0}}}}; "
                             f"the names are the plant's fields: {names}.")
    parser.add_argument("--evaluation", type=EvaluationConfig, default=EvaluationConfig(),
                        help="Closed-loop evaluation settings.")
    parser.add_argument("--allow_long", type=bool, default=False,
                        help="Run an experiment estimated to take more than a day (refused otherwise).")
    parser.add_argument("--reference", type=dict[str, dict[str, float]] | None, default=None,
                        help="Published numbers (scenario -> controller -> median RMS nm) shown beside ours.")
