"""The ``eofnn`` command line: ``fit``, ``compare`` and ``evaluate``, configured by YAML (jsonargparse).

Every value of a config can be overridden on the command line with its dotted key, e.g.
``--predictors.cl_eof.history_length 8`` or ``--scenario.atmosphere.r0_m 0.1``. Networks are named by
``class_path`` (any ``torch.nn.Module`` importable from Python) and ``init_args``.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path
from typing import Any

import yaml
from jsonargparse import ActionConfigFile, ArgumentParser, DefaultHelpFormatter
from jsonargparse import ArgumentError as JsonArgError

from eofnn.errors import CheckpointError, ConfigError, DivergedError, TelemetryError
from eofnn.evaluation.experiment import (
    EvaluationConfig,
    Experiment,
    ExperimentResult,
    PredictorConfig,
    check_output_dir,
    fit_from_config,
    save_timeseries,
    write_metrics,
)
from eofnn.sim.scenario import Scenario
from eofnn.sweep import build_sweep_parser, run_sweep

DESCRIPTION = """\
eofnn: predictive wavefront control for adaptive optics, in simulated closed loop.

  eofnn compare  --config configs/paper.yaml --out results/paper   # scenarios x predictors, one command
  eofnn fit      --config configs/fit_cl_eof.yaml --out runs/cl_eof.ckpt  # train one predictor, save it
  eofnn evaluate --config configs/evaluate.yaml --out results/eval  # saved checkpoints under any plant
  eofnn simulate --scenario configs/reference.yaml --out run.fits     # one controller -> telemetry + plot
  eofnn sweep    --config configs/paper_small.yaml --grid GRID.yaml --out results/sweep  # a grid of compares

Each subcommand takes --config FILE (YAML) and dotted overrides; '<subcommand> --help' lists them all,
'<subcommand> --print_config' prints the resolved configuration.
"""

USER_ERRORS = (ConfigError, CheckpointError, TelemetryError, DivergedError, FileExistsError, JsonArgError)


class _HelpFormatter(DefaultHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Keeps the examples in the descriptions laid out as written."""


def _common(parser: ArgumentParser, out_help: str) -> None:
    parser.add_argument("--config", action=ActionConfigFile, help="YAML configuration file.")
    parser.add_argument("--scenario", type=Scenario, default=Scenario(),
                        help="Telescope (grid), atmosphere, frame rate, delay and base model errors.")
    parser.add_argument("--out", type=str, required=True, help=out_help)
    parser.add_argument("--overwrite", type=bool, default=False, help="Replace existing output.")
    parser.add_argument("--progress", type=bool | None, default=None,
                        help="Progress bars (default: only when stderr is a terminal).")


def _evaluation_args(parser: ArgumentParser) -> None:
    parser.add_argument("--scenarios", type=dict[str, dict[str, Any]], default={"nominal": {}},
                        help="Scenario name -> model errors, e.g. {nominal: {}, dm_gain_2: {dm_gain: 2.0}}.")
    parser.add_argument("--evaluation", type=EvaluationConfig, default=EvaluationConfig(),
                        help="Closed-loop evaluation settings.")
    parser.add_argument("--reference", type=dict[str, dict[str, float]] | None, default=None,
                        help="Published numbers (scenario -> predictor -> median RMS nm) shown beside ours.")


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="eofnn", description=DESCRIPTION, exit_on_error=False, formatter_class=_HelpFormatter)
    sub = parser.add_subcommands(dest="command")

    fit = ArgumentParser(description="Train one predictor on telemetry simulated in a scenario and save a "
                         "Lightning checkpoint that compare/evaluate can reuse.", exit_on_error=False)
    _common(fit, "Checkpoint file to write (.ckpt).")
    fit.add_argument("--predictor", type=PredictorConfig, default=PredictorConfig(),
                     help="History, network, fit method and training data of the predictor.")
    sub.add_subcommand("fit", fit, help="Train one predictor and write a checkpoint.")

    compare = ArgumentParser(description="Run an experiment: every predictor in every scenario (plant), "
                             "trained once where asked, evaluated in closed loop on a held-out stream. Writes "
                             "metrics.json, results.md, config.yaml, figures and checkpoints into --out.",
                             exit_on_error=False)
    _common(compare, "Output folder (must be empty unless --overwrite true).")
    _evaluation_args(compare)
    compare.add_argument("--predictors", type=dict[str, PredictorConfig], required=True,
                         help="Predictor name -> configuration.")
    sub.add_subcommand("compare", compare, help="Scenarios x predictors: train, evaluate, report.")

    evaluate = ArgumentParser(description="Evaluate saved checkpoints (from fit or compare) in any scenario, "
                              "without retraining, beside baseline controllers.", exit_on_error=False)
    _common(evaluate, "Output folder (must be empty unless --overwrite true).")
    _evaluation_args(evaluate)
    evaluate.add_argument("--checkpoints", type=dict[str, str], required=True,
                          help="Name -> checkpoint path.")
    evaluate.add_argument("--baselines", type=list[str], default=["uncorrected", "pseudo_integrator", "integrator"],
                          help="Baseline controllers to run beside the checkpoints.")
    sub.add_subcommand("evaluate", evaluate, help="Run saved checkpoints under any plant.")

    simulate = ArgumentParser(description="Run one controller (a baseline or a checkpoint) in a scenario and save "
                              "its telemetry (s, y, eps, wfs in nm) as FITS or .npz, with a plot of the RMS residual "
                              "beside it.", exit_on_error=False)
    _common(simulate, "Telemetry file to write (.fits or .npz); the plot goes to the same name with .png.")
    simulate.add_argument("--predictor", type=PredictorConfig, default=PredictorConfig(controller="integrator"),
                          help="The controller: controller: uncorrected|pseudo_integrator|integrator, or checkpoint.")
    simulate.add_argument("--frames", type=int, default=2000, help="Frames to simulate.")
    simulate.add_argument("--realisations", type=int, default=1, help="Independent realisations (batch).")
    simulate.add_argument("--seed", type=int, default=1, help="Seed of the turbulence and noise.")
    sub.add_subcommand("simulate", simulate, help="Simulate one controller and save telemetry.")
    sub.add_subcommand("sweep", build_sweep_parser(), help="A grid of compare runs: resumable, local or on Ray.")
    return parser


def _one_line(err: BaseException) -> str:
    """Collapse jsonargparse's nested messages into one line."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    lines = [line for line in lines if not line.startswith("Problem with given class_path")]
    return ": ".join(lines).replace('Parser key "', "").replace('":', ":")


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run_fit(cfg, config_dump: str) -> dict:
    p: PredictorConfig = cfg.predictor
    scenario: Scenario = cfg.scenario
    if p.controller != "predictor" or p.checkpoint is not None:
        raise ConfigError(f"fit trains a predictor: controller={p.controller!r}, checkpoint={p.checkpoint!r} "
                          "cannot be fitted")
    out = Path(cfg.out)
    config_out = out.with_name(out.name + ".yaml")  # beside the checkpoint, never a user's own config file
    for path in (out, config_out):
        if path.exists() and not cfg.overwrite:
            raise ConfigError(f"{str(path)!r} exists: choose another --out or pass --overwrite true")
    _log(f"fitting {p.history} predictor, history {p.history_length}, {p.fit_method}, {p.training.frames} frames")
    result = fit_from_config(scenario, p, out, overwrite=cfg.overwrite, progress=bool(cfg.progress))
    config_out.write_text(config_dump)
    summary = {"checkpoint": str(out), "train_loss_nm2": result.train_loss, "val_loss_nm2": result.val_loss,
               "rounds": result.rounds}
    _log(json.dumps(summary))
    return summary


def run_simulate(cfg, config_dump: str) -> None:
    from eofnn.evaluation.metrics import loop_metrics
    from eofnn.evaluation.report import plot_rms_vs_time
    from eofnn.sim.loop import run_loop

    out = Path(cfg.out)
    if out.suffix.lower() not in (".fits", ".fit", ".npz"):
        raise ConfigError(f"out={str(out)!r} has suffix {out.suffix!r}: allowed are .fits, .npz")
    plot = out.with_suffix(".png")
    for path in (out, plot):
        if path.exists() and not cfg.overwrite:
            raise ConfigError(f"{str(path)!r} exists: choose another --out or pass --overwrite true")
    if cfg.predictor.controller == "predictor" and cfg.predictor.checkpoint is None:
        raise ConfigError("simulate runs a baseline or a checkpoint: set predictor.controller or predictor.checkpoint")
    if cfg.frames < 1 or cfg.realisations < 1:
        raise ConfigError(f"frames={cfg.frames!r}, realisations={cfg.realisations!r}: both must be >= 1")
    experiment = Experiment(cfg.scenario, {"scenario": {}}, {"controller": cfg.predictor},
                            EvaluationConfig(frames=cfg.frames, settle_frames=0), log=_log)
    scenario = experiment.scenarios["scenario"]
    result = run_loop(scenario.turbulence(cfg.seed, "test", cfg.realisations), scenario.plant,
                      experiment.controller("controller", "scenario"), cfg.frames, noise_seed=cfg.seed,
                      progress=cfg.progress)
    telemetry = result.telemetry if cfg.realisations > 1 else result.telemetry.realisation(0)
    telemetry.config.update({"eofnn": yaml.safe_load(config_dump), "diverged_frame": result.diverged_frame})
    out.parent.mkdir(parents=True, exist_ok=True)
    telemetry.save(out, overwrite=cfg.overwrite)
    metrics = loop_metrics(result, 0, EvaluationConfig().strehl_wavelength_m)
    plot_rms_vs_time(ExperimentResult({"scenario": {"controller": metrics}}), scenario.frame_rate_hz, plot)
    _log(json.dumps({"telemetry": str(out), "plot": str(plot), **metrics.summary()}))


def run_experiment(cfg, predictors: dict[str, PredictorConfig], config_dump: str):
    from eofnn.evaluation.report import write_report

    out = check_output_dir(cfg.out, cfg.overwrite)
    experiment = Experiment(cfg.scenario, cfg.scenarios, predictors, cfg.evaluation,
                            checkpoint_dir=out / "checkpoints", progress=cfg.progress, log=_log)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(config_dump)
    result = experiment.run()
    write_metrics(result, out / "metrics.json")
    save_timeseries(result, out / "timeseries.npz")
    write_report(result, out, cfg.scenario.frame_rate_hz, cfg.reference)
    _log(f"results in {out}/ (metrics.json, results.md, figures)")
    return result


def main(args: list[str] | None = None) -> int:
    """Entry point of the ``eofnn`` console script; returns the exit status."""
    parser = build_parser()
    try:
        cfg = parser.parse_args(args)
        command = cfg.command
        dump = parser.dump(cfg)
        sub_dump = yaml.safe_dump({k: v for k, v in yaml.safe_load(dump)[command].items() if k != "config"},
                                  sort_keys=False)
        init = parser.instantiate(cfg)[command]
        with warnings.catch_warnings():
            # Lightning's hints for big training jobs (more DataLoader workers) do not apply to simulated streams.
            warnings.filterwarnings("ignore", message=".*does not have many workers.*")
            # Lightning's own use of a deprecated torch pytree API, nothing a user can act on.
            warnings.filterwarnings("ignore", message=".*isinstance\\(treespec, LeafSpec\\)` is deprecated.*")
            if command == "fit":
                run_fit(init, sub_dump)
            elif command == "compare":
                run_experiment(init, init.predictors, sub_dump)
            elif command == "simulate":
                run_simulate(init, sub_dump)
            elif command == "sweep":
                return run_sweep(init)
            else:
                predictors = {name: PredictorConfig(controller=name) for name in init.baselines}
                for name, path in init.checkpoints.items():
                    predictors[name] = PredictorConfig(checkpoint=path)
                run_experiment(init, predictors, sub_dump)
    except USER_ERRORS as err:
        print(f"eofnn: error: {_one_line(err)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())


def console() -> None:
    """Console-script wrapper: exit with :func:`main`'s status."""
    sys.exit(main())
