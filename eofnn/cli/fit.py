"""``eofnn fit``: train one predictor on telemetry simulated in a scenario and save its checkpoint."""

from __future__ import annotations

import json
from pathlib import Path

from jsonargparse import ArgumentParser

from eofnn.cli.common import add_common, log
from eofnn.cli.telemetry import add_fit_telemetry_arguments, run_fit_telemetry
from eofnn.errors import ConfigError
from eofnn.evaluation.config import PredictorConfig
from eofnn.evaluation.experiment import fit_from_config
from eofnn.outputs import check_output_file, staged_file
from eofnn.training.fit import FitOutput

DESCRIPTION = ("Train one predictor on telemetry simulated in a scenario (simulator truth) or, with --telemetry, on "
               "recorded telemetry alone through an identified plant, and save a Lightning checkpoint that compare "
               "and evaluate can reuse (its resolved config goes beside it, as CHECKPOINT.yaml).")


def add_arguments(parser: ArgumentParser) -> None:
    add_common(parser, "Checkpoint file to write (.ckpt).")
    parser.add_argument("--predictor", type=PredictorConfig, default=PredictorConfig(),
                        help="History, network, data and optimisation of the predictor.")
    add_fit_telemetry_arguments(parser)


def run(cfg, config_dump: str) -> dict:
    p: PredictorConfig = cfg.predictor
    if not p.trains:
        raise ConfigError(f"fit trains a predictor: controller={p.controller!r}, checkpoint={p.checkpoint!r} "
                          "cannot be fitted")
    out = Path(cfg.out)
    config_out = out.with_name(out.name + ".yaml")  # beside the checkpoint, never a user's own config file
    check_output_file(out, cfg.overwrite)
    check_output_file(config_out, cfg.overwrite)
    if cfg.telemetry:
        result = run_fit_telemetry(cfg, config_dump, out)
    else:
        log(f"fitting {p.history} predictor, history {p.history_length}, {p.optimization.fit_method}, "
            f"{p.data.frames} frames (simulator truth)")
        result = fit_from_config(cfg.scenario, p, FitOutput(out, cfg.overwrite, bool(cfg.progress)))
    with staged_file(config_out, overwrite=True) as partial:
        partial.write_text(config_dump)
    summary = {"checkpoint": str(out), "train_loss_nm2": result.train_loss, "val_loss_nm2": result.val_loss,
               "rounds": result.rounds, "targets": "telemetry" if cfg.telemetry else "simulator truth"}
    log(json.dumps(summary))
    return summary
