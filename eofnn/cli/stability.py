"""``eofnn stability``: analytic stability margins of a checkpoint's linear filter in a scenario's plant."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

from eofnn.cli.common import config_yaml, log
from eofnn.cli.groups import SimulationCommand
from eofnn.control.registry import NEEDS_PREDICTOR
from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
from eofnn.outputs import check_output_folder, staged_folder
from eofnn.validation import Interval, OrNone, check_value

DESCRIPTION = ("Analytic stability of a checkpoint's linear filter (per actuator, shared or neighbourhood), or of a "
               "classical controller (--controller: integrator, extrapolator, modal_integrator, lqg, pfc; the last "
               "three built from telemetry recorded in the scenario), in the scenario's plant: stable or not, the interval "
               "of DM gain that keeps it stable, the delay margin, and the rejection and noise transfer functions. "
               "Writes stability.json and stability.png into --out.")


@dataclass(kw_only=True)
class StabilityConfig(SimulationCommand):
    """``eofnn stability``: the analytic margins of one linear controller.

    Parameters
    ----------
    checkpoint : str, optional
        Checkpoint of a linear predictor (.ckpt); or give --controller.
    controller : PredictorConfig, optional
        A classical controller to analyse instead of a checkpoint, e.g. {controller: lqg, data: {frames: 10000}}
        (modal_integrator, lqg and pfc record their telemetry in the scenario).
    dm_gain_model : float, optional
        DM gain the controller believes (its pseudo-open-loop reconstruction); unset, the checkpoint's own
        (identified from telemetry, or 1).
    """

    checkpoint: str | None = None
    controller: PredictorConfig | None = None
    dm_gain_model: float | None = None


def stability(cfg: StabilityConfig, config_dump: str | None = None) -> dict:
    """Analyse the checkpoint's filter or the classical controller in ``cfg.scenario``'s plant; writes
    ``stability.json``, ``stability.png`` and ``config.yaml`` into ``cfg.out`` and returns the summary line."""
    check_value("dm_gain_model", cfg.dm_gain_model, OrNone(Interval(0, 100, closed="right")))
    if (cfg.checkpoint is None) == (cfg.controller is None):
        raise ConfigError("give either --checkpoint (a trained linear predictor) or --controller (a classical "
                          "controller), not both or neither")
    out = check_output_folder(cfg.out, cfg.overwrite)
    # The analysis, checkpoints and the figure import torch and matplotlib (seconds): only when the command runs.
    from eofnn.analysis.linear import controller_stability, summary
    from eofnn.reporting.stability import plot_stability
    from eofnn.training.checkpoint import load_predictor

    if cfg.checkpoint is not None:
        predictor = load_predictor(cfg.checkpoint, cfg.scenario, trusted_networks=cfg.trusted_networks)
        config = PredictorConfig(checkpoint=cfg.checkpoint, dm_gain_model=cfg.dm_gain_model)
        what = cfg.checkpoint
        result = controller_stability(config, predictor, cfg.scenario)
        if result is None:
            raise ConfigError(f"checkpoint {cfg.checkpoint!r} holds a {type(predictor.network).__name__}: the analytic "
                              "stability analysis needs a linear filter (eofnn.models.linear.LinearFilter)")
    else:
        result, what = classical_stability(cfg.controller, cfg.scenario, cfg.dm_gain_model), cfg.controller.controller
    line = summary(result, cfg.scenario)  # a pyramid's: with the stable optical-gain interval
    full = result.to_dict()
    if "optical_gain" in line:
        full["optical_gain"] = line["optical_gain"]
    with staged_folder(out, cfg.overwrite) as staging:
        (staging / "stability.json").write_text(json.dumps(full, indent=1))
        (staging / "config.yaml").write_text(config_yaml(cfg, config_dump))
        plot_stability(result, staging / "stability.png", f"{what}")
    keys = ("stable", "dm_gain_interval", "delay_margin_frames", "max_root_modulus", "optical_gain")
    log(json.dumps({k: line[k] for k in keys if k in line}))
    return line


def classical_stability(controller: PredictorConfig, scenario, dm_gain_model: float | None):
    """The analysis of a classical controller as ``compare`` would make it in ``scenario`` (a best-gain integrator's
    scan and a modal model's telemetry on streams of their own)."""
    if controller.controller in NEEDS_PREDICTOR:
        raise ConfigError(f"--controller.controller={controller.controller!r} runs a trained network: give its "
                          "--checkpoint instead")
    if dm_gain_model is not None:
        controller = replace(controller, dm_gain_model=dm_gain_model)
    from eofnn.analysis.linear import controller_stability
    from eofnn.evaluation.experiment import Experiment

    experiment = Experiment(scenario, {"nominal": {}}, {"controller": controller}, EvaluationConfig(),
                            log=log)
    result = controller_stability(experiment.config("controller", "nominal"),
                                  experiment.predictor_if_any("controller", "nominal"), scenario)
    if result is None:
        raise ConfigError(f"controller={controller.controller!r} has no linear model to analyse")
    return result
