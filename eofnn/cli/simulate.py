"""``eofnn simulate``: run one controller (a baseline or a checkpoint) and save its telemetry and an RMS plot."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from eofnn.cli.common import config_yaml, log
from eofnn.cli.groups import SimulationCommand
from eofnn.control.registry import NEEDS_PREDICTOR, build_controller
from eofnn.errors import ConfigError
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
from eofnn.outputs import check_output_file, claim_output, staged_file
from eofnn.resources import require_memory
from eofnn.sim.loop.runner import run_loop
from eofnn.validation import Interval, OneOf, check_value

DESCRIPTION = ("Run one controller (a baseline or a checkpoint) in a scenario and save its telemetry (s, y, eps, wfs "
               "in nm; with a Shack-Hartmann also its slopes, interaction matrix and reconstructor) as FITS or .npz, "
               "with a plot of the RMS residual beside it.")
SUFFIXES = (".fits", ".fit", ".npz")


@dataclass(kw_only=True)
class SimulateConfig(SimulationCommand):
    """``eofnn simulate``: one controller's telemetry.

    Parameters
    ----------
    out : str
        Telemetry file to write (.fits or .npz); the plot goes to the same name with .png.
    predictor : PredictorConfig
        The controller: controller: uncorrected|pseudo_integrator|integrator, or controller: predictor with a
        checkpoint.
    frames : int
        Frames to simulate.
    realisations : int
        Independent realisations (batch).
    seed : int
        Seed of the turbulence and noise.
    dtype : str
        Precision of the saved arrays: float64, or float32 (half the size; nm to 7 digits).
    """

    predictor: PredictorConfig = field(default_factory=lambda: PredictorConfig(controller="integrator"))
    frames: int = 2000
    realisations: int = 1
    seed: int = 1
    dtype: str = "float64"


def simulate(cfg: SimulateConfig, config_dump: str | None = None) -> None:
    """Run ``cfg.predictor`` in ``cfg.scenario`` and write its telemetry to ``cfg.out`` and an RMS plot beside it.

    Its outputs are claimed (:func:`eofnn.outputs.claim_output`) before any work: a second run into the same
    ``out`` meanwhile is refused in one line.
    """
    out = Path(cfg.out)
    with claim_output(out), claim_output(out.with_name(out.name + ".png")):
        return _simulate(cfg, config_dump)


def _simulate(cfg: SimulateConfig, config_dump: str | None = None) -> None:
    """:func:`simulate` once its outputs are claimed."""
    out = Path(cfg.out)
    if out.suffix.lower() not in SUFFIXES:
        raise ConfigError(f"out={str(out)!r} has suffix {out.suffix!r}: allowed are {', '.join(SUFFIXES)}")
    plot = out.with_name(out.name + ".png")  # run.fits -> run.fits.png: a .fits and an .npz never share a plot
    check_output_file(out, cfg.overwrite)
    check_output_file(plot, cfg.overwrite)
    check_value("frames", cfg.frames, Interval(1, 10_000_000, integer=True))
    check_value("realisations", cfg.realisations, Interval(1, 1024, integer=True))
    check_value("seed", cfg.seed, Interval(0, 2**63 - 1, integer=True))
    check_value("dtype", cfg.dtype, OneOf(("float64", "float32")))
    p: PredictorConfig = cfg.predictor
    predictor = None
    if p.controller in NEEDS_PREDICTOR and p.checkpoint is None:
        raise ConfigError("simulate runs a baseline or a checkpoint: set predictor.controller to a baseline or "
                          "give predictor.checkpoint")
    # The evaluation and the figure import torch's users and matplotlib (seconds): only once the values are checked.
    from eofnn.evaluation.contenders import load_configured_checkpoint, trusted_class_paths
    from eofnn.evaluation.metrics import loop_metrics
    from eofnn.evaluation.results import ExperimentResult
    from eofnn.reporting.report import plot_rms_vs_time

    scenario = cfg.scenario
    # Telemetry keeps s, y, eps, wfs of every frame in float64, and a Shack-Hartmann's slopes (fewer than 2 per
    # actuator: counted as 2) beside them.
    slopes = scenario.sensor.is_shack_hartmann
    require_memory((6 if slopes else 4) * 8 * cfg.frames * cfg.realisations * scenario.grid.n_actuators,
                   f"simulate with frames={cfg.frames}, realisations={cfg.realisations} and "
                   f"{scenario.grid.n_actuators} actuators")
    scenario.require_stream_frames(cfg.frames, f"frames={cfg.frames}", cfg.realisations)
    scenario.require_changes_within(cfg.frames, "scenario")
    if p.controller in NEEDS_PREDICTOR:
        predictor = load_configured_checkpoint("controller", p, {"scenario": scenario},
                                               trusted_class_paths({"controller": p}, cfg.trusted_networks))
    # A Shack-Hartmann's slopes go beside wfs, with the matrices that make wfs of them: readers use wfs, and a copy
    # without it is read as anyone's slopes (docs/telemetry.md); telemetry.config["sensor"] says which sensor.
    settle = min(EvaluationConfig().settle_frames, cfg.frames // 2)
    turbulence, probe = scenario.turbulence(cfg.seed, "test", cfg.realisations), None
    if scenario.sensor.is_pyramid and p.controller == "integrator":  # its optical gains on the closed-loop residual
        from eofnn.sim.sensing.optical_gains import OpticalGainProbe

        probe = OpticalGainProbe.of(turbulence, settle, cfg.frames, scenario.plant)
    result = run_loop(turbulence, scenario.plant,
                      build_controller(p, predictor), cfg.frames, noise_seed=cfg.seed, progress=cfg.progress,
                      record=("s", "y", "eps", "wfs", *(("slopes",) if slopes else ())), on_chunk=probe)
    telemetry = result.telemetry if cfg.realisations > 1 else result.telemetry.realisation(0)
    telemetry.config.update({"eofnn": yaml.safe_load(config_yaml(cfg, config_dump)),
                             "diverged_frame": result.diverged_frame})
    metrics = loop_metrics(result, settle, EvaluationConfig().strehl_wavelength_m)
    if probe is not None and not result.diverged:
        metrics.optical_gains = probe.result()
    with staged_file(out, cfg.overwrite) as partial:
        telemetry.save(partial, overwrite=True, dtype=cfg.dtype)
    with staged_file(plot, cfg.overwrite) as partial:
        plot_rms_vs_time(ExperimentResult({"scenario": {p.controller: metrics}}), scenario.frame_rate_hz, partial)
    log(json.dumps({"telemetry": str(out), "plot": str(plot), **metrics.summary(),
                    "strehl_wavelength_m": EvaluationConfig().strehl_wavelength_m}))
