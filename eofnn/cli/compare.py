"""``eofnn compare`` and ``eofnn evaluate``: scenarios x controllers in closed loop, written to one folder."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import eofnn
from eofnn.cli.common import config_yaml, log
from eofnn.cli.groups import ExperimentCommand
from eofnn.control.config import FallbackConfig
from eofnn.errors import ConfigError
from eofnn.evaluation.config import PredictorConfig
from eofnn.outputs import check_output_folder, staged_folder
from eofnn.validation import from_mapping

# The experiment, its analyses and figures import torch, Lightning, HCIPy and matplotlib (seconds): imported when the
# command runs, so that the parser (built from the dataclasses below) and config errors answer without them.
# Annotations name heavy types by their module path (``import eofnn``), never in a TYPE_CHECKING block: jsonargparse
# runs a config module's TYPE_CHECKING imports when it reads the config's types, which would import torch & co.

COMPARE = ("Run an experiment: every controller in every scenario (plant), predictors trained once where asked, "
           "evaluated in closed loop on a held-out stream. Writes metrics.json, results.md, config.yaml, figures, "
           "timeseries.npz and checkpoints/ into --out, all at once when the run is complete.")
EVALUATE = ("Evaluate saved checkpoints (from fit or compare) in any scenario, without retraining, beside "
            "baseline controllers.")


@dataclass(kw_only=True)
class CompareConfig(ExperimentCommand):
    """``eofnn compare``: every controller in every scenario.

    Parameters
    ----------
    predictors : dict
        Controller name -> configuration.
    robustness : dict, optional
        Plant field -> values, e.g. {dm_gain: [0.5, 1, 1.5, 2, 3]} (one or two fields): every controller, as made for
        the first scenario, runs in each plant; writes robustness.json and robustness.png with the analytic
        stability bounds.
    simulated_margins : list of str
        Scenarios in which the DM-gain interval of every controller without a linear model (networks) is measured by
        closed-loop simulation, each bound bracketed within 5% (metrics.json: simulated_stability; results.md).
    pareto : bool or str
        Also draw every linear controller family along its tuning path (ridge alphas of alpha: auto, integrator
        gains) in the first scenario (true) or the one named, median RMS on a stream of its own against the width of
        the stable DM-gain interval: pareto.png, pareto.md, pareto.json.
    """

    predictors: dict[str, PredictorConfig]
    robustness: dict[str, list[float]] | None = None
    simulated_margins: list[str] = field(default_factory=list)
    pareto: bool | str = False


@dataclass(kw_only=True)
class EvaluateConfig(ExperimentCommand):
    """``eofnn evaluate``: saved checkpoints beside baselines.

    Parameters
    ----------
    checkpoints : dict
        Name -> checkpoint path.
    baselines : list of str
        Baseline controllers to run beside the checkpoints.
    integrator : PredictorConfig
        The integrator of baselines: a fixed gain (gain, default 0.5), or compare's best-gain integrator, gains:
        [0.2, 0.3, 0.4, 0.5, 0.6] (in each scenario the loop is closed with each gain on a stream of its own,
        data.frames frames, refined around the best; the fair baseline). metrics.json (integrator_gain_used),
        results.md and the progress line say the gain it ran at.
    fallback : FallbackConfig
        Never worse than the integrator, for every checkpoint: ``per: whole`` or ``per: mode`` deploys it only where
        it beats the best-gain integrator on a validation stream of its own (``modes``, ``gains``, ``frames``,
        ``realisations``, ``blocks``, ``sigmas``, ``seed``); metrics.json ``fallback`` and results.md say which
        modes fell back and why. Off (``per: none``) by default.
    """

    checkpoints: dict[str, str]
    baselines: list[str] = field(default_factory=lambda: ["uncorrected", "pseudo_integrator", "integrator"])
    integrator: PredictorConfig = field(default_factory=lambda: PredictorConfig(controller="integrator"))
    fallback: FallbackConfig = field(default_factory=FallbackConfig)


def run_experiment(cfg: ExperimentCommand, predictors: dict[str, PredictorConfig], config_dump: str | None = None, *,
                   robustness: dict[str, list[float]] | None = None, simulated_margins: Sequence[str] = (),
                   pareto_scenario: bool | str = False) -> eofnn.evaluation.results.ExperimentResult:
    """Check the output folder and plan the compare (:func:`eofnn.evaluation.stages.plan_compare`: everything checked),
    then run its stages (the experiment, then the analyses ``robustness``, ``simulated_margins`` and
    ``pareto_scenario`` as :class:`CompareConfig` describes them) and write the results in one move."""
    from eofnn.evaluation.stages import plan_compare, run_compare
    from eofnn.reporting.experiment import write_experiment

    out = check_output_folder(cfg.out, cfg.overwrite)
    plan = plan_compare(cfg.scenario, cfg.scenarios, predictors, cfg.evaluation, robustness=robustness,
                        simulated_margins=simulated_margins, pareto=pareto_scenario, progress=cfg.progress, log=log,
                        trusted_networks=cfg.trusted_networks, allow_long=cfg.allow_long)
    with staged_folder(out, cfg.overwrite) as staging:
        plan.experiment.checkpoint_dir = staging / "checkpoints"
        (staging / "config.yaml").write_text(config_yaml(cfg, config_dump))
        result, analyses = run_compare(plan, log)
        write_experiment(staging, result, analyses, cfg.scenario.frame_rate_hz, cfg.reference,
                         cfg.evaluation.strehl_wavelength_m)
    log(f"results in {Path(out)}/ (metrics.json, results.md, figures)")
    return result


def compare(cfg: CompareConfig, config_dump: str | None = None) -> eofnn.evaluation.results.ExperimentResult:
    """Run ``cfg.predictors`` in every scenario and write the results into ``cfg.out`` (``config_dump``: the resolved
    YAML written as ``config.yaml``; the config's own YAML when called from Python)."""
    return run_experiment(cfg, cfg.predictors, config_dump, robustness=cfg.robustness,
                          simulated_margins=cfg.simulated_margins, pareto_scenario=cfg.pareto)


def evaluate(cfg: EvaluateConfig, config_dump: str | None = None) -> eofnn.evaluation.results.ExperimentResult:
    """Run ``cfg.checkpoints`` beside ``cfg.baselines`` in every scenario and write the results into ``cfg.out``."""
    integrator = cfg.integrator
    if isinstance(integrator, dict):  # called from Python with a mapping
        integrator = from_mapping(PredictorConfig, {"controller": "integrator", **integrator}, "integrator")
    if integrator.controller != "integrator":
        raise ConfigError(f"integrator.controller={integrator.controller!r} is invalid: it must be integrator (the "
                          "integrator of baselines)")
    if "integrator" not in cfg.baselines and integrator != PredictorConfig(controller="integrator"):
        raise ConfigError(f"integrator is set but baselines={cfg.baselines!r} has no integrator: add it, or leave "
                          "integrator out")
    predictors = {name: integrator if name == "integrator" else PredictorConfig(controller=name)
                  for name in cfg.baselines}
    fallback = cfg.fallback if not isinstance(cfg.fallback, dict) else from_mapping(FallbackConfig, cfg.fallback,
                                                                                    "fallback")
    for name, path in cfg.checkpoints.items():
        predictors[name] = PredictorConfig(checkpoint=path, fallback=fallback)
    return run_experiment(cfg, predictors, config_dump)
