"""``eofnn fit``: train one predictor on telemetry simulated in a scenario and save its checkpoint."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from eofnn.cli.common import TelemetryFiles, config_yaml, log
from eofnn.cli.groups import SimulationCommand
from eofnn.cli.telemetry import PLANT_HELP, fit_telemetry
from eofnn.errors import ConfigError
from eofnn.evaluation.config import PredictorConfig
from eofnn.outputs import check_output_file, claim_output, staged_file

DESCRIPTION = ("Train one predictor on telemetry simulated in a scenario (simulator truth) or, with --telemetry, on "
               "recorded telemetry alone through an identified plant, and save a Lightning checkpoint that compare "
               "and evaluate can reuse (its resolved config goes beside it, as CHECKPOINT.yaml).")


@dataclass(kw_only=True)
class FitConfig(TelemetryFiles, SimulationCommand):
    """``eofnn fit``: one predictor, from simulator truth or from telemetry alone.

    Parameters
    ----------
    out : str
        Checkpoint file to write (.ckpt).
    predictor : PredictorConfig
        History, network, data and optimisation of the predictor.
    telemetry : str or list of str, optional
        Train from these telemetry files alone (y, wfs) instead of simulating the scenario; the last
        predictor.data.val_frames frames (at most a fifth) are held out for validation.
    plant : str
        With --telemetry: {plant_help}
    """

    predictor: PredictorConfig = field(default_factory=PredictorConfig)
    telemetry: str | list[str] | None = None
    plant: str = "identify"


FitConfig.__doc__ = FitConfig.__doc__.replace("{plant_help}", PLANT_HELP)


def fit(cfg: FitConfig, config_dump: str | None = None) -> dict:
    """Fit ``cfg.predictor`` and write its checkpoint to ``cfg.out`` and its resolved config beside it; returns the
    summary line (losses, rounds, where the targets came from).

    Its outputs are claimed (:func:`eofnn.outputs.claim_output`) before any work: a second run into the same
    ``out`` meanwhile is refused in one line.
    """
    out = Path(cfg.out)
    with claim_output(out), claim_output(out.with_name(out.name + ".yaml")):
        return _fit(cfg, config_dump)


def _fit(cfg: FitConfig, config_dump: str | None = None) -> dict:
    """:func:`fit` once its outputs are claimed."""
    p: PredictorConfig = cfg.predictor
    if not p.trains:
        raise ConfigError(f"fit trains a predictor: controller={p.controller!r}, checkpoint={p.checkpoint!r} "
                          "cannot be fitted")
    out = Path(cfg.out)
    config_out = out.with_name(out.name + ".yaml")  # beside the checkpoint, never a user's own config file
    check_output_file(out, cfg.overwrite)
    check_output_file(config_out, cfg.overwrite)
    if cfg.telemetry:
        result = fit_telemetry(cfg, out)
    else:
        from eofnn.evaluation.contenders import fit_from_config  # torch, Lightning: only when the fit runs
        from eofnn.training.fit import FitOutput

        log(f"fitting {p.history} predictor, history {p.history_length}, {p.optimization.fit_method}, "
            f"{p.data.frames} frames (simulator truth)")
        result = fit_from_config(cfg.scenario, p, FitOutput(out, cfg.overwrite, bool(cfg.progress)))
    with staged_file(config_out, overwrite=True) as partial:
        partial.write_text(config_yaml(cfg, config_dump))
    summary = {"checkpoint": str(out), "train_loss_nm2": result.train_loss, "val_loss_nm2": result.val_loss,
               "rounds": result.rounds, "targets": "telemetry" if cfg.telemetry else "simulator truth"}
    if "through_loop" in result.info:  # closed-loop residuals (nm^2) of the closed-form start and of the result
        loop = result.info["through_loop"]
        summary["through_loop"] = {"start_val_residual_nm2": loop["start"]["val_residual_nm2"],
                                   "val_residual_nm2": loop["val_residual_nm2"], "best_epoch": loop["best_epoch"]}
    log(json.dumps(summary))
    return summary
