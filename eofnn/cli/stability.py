"""``eofnn stability``: analytic stability margins of a checkpoint's linear filter in a scenario's plant."""

from __future__ import annotations

import json

from jsonargparse import ArgumentParser

from eofnn.analysis.figures import plot_stability
from eofnn.analysis.linear import controller_stability, summary
from eofnn.cli.common import add_common, log
from eofnn.errors import ConfigError
from eofnn.evaluation.config import PredictorConfig
from eofnn.outputs import check_output_folder, staged_folder
from eofnn.training.checkpoint import load_predictor
from eofnn.validation import Interval, OrNone, check_value

DESCRIPTION = ("Analytic stability of a checkpoint's linear filter (per actuator, shared or neighbourhood) in the "
               "scenario's plant: stable or not, the interval of DM gain that keeps it stable, the delay margin, and "
               "the rejection and noise transfer functions. Writes stability.json and stability.png into --out.")


def add_arguments(parser: ArgumentParser) -> None:
    add_common(parser, "Output folder (must be empty unless --overwrite true).")
    parser.add_argument("--checkpoint", type=str, required=True, help="Checkpoint of a linear predictor (.ckpt).")
    parser.add_argument("--dm_gain_model", type=float | None, default=None,
                        help="DM gain the controller believes (its pseudo-open-loop reconstruction); unset, the "
                             "checkpoint's own (identified from telemetry, or 1).")


def run(cfg, config_dump: str) -> dict:
    check_value("dm_gain_model", cfg.dm_gain_model, OrNone(Interval(0, 100, closed="right")))
    out = check_output_folder(cfg.out, cfg.overwrite)
    predictor = load_predictor(cfg.checkpoint, cfg.scenario, trusted_networks=cfg.trusted_networks)
    config = PredictorConfig(checkpoint=cfg.checkpoint, dm_gain_model=cfg.dm_gain_model)
    result = controller_stability(config, predictor, cfg.scenario)
    if result is None:
        raise ConfigError(f"checkpoint {cfg.checkpoint!r} holds a {type(predictor.network).__name__}: the analytic "
                          "stability analysis needs a linear filter (eofnn.models.linear.LinearFilter)")
    with staged_folder(out, cfg.overwrite) as staging:
        (staging / "stability.json").write_text(result.to_json())
        (staging / "config.yaml").write_text(config_dump)
        plot_stability(result, staging / "stability.png", f"{cfg.checkpoint}")
    line = summary(result)
    log(json.dumps({k: line[k] for k in ("stable", "dm_gain_interval", "delay_margin_frames", "max_root_modulus")}))
    return line
