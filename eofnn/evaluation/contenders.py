"""An experiment's contenders, before any loop is scored: the scenarios they run in, the checks made up front
(memory, time, streams, checkpoints), how each predictor is trained, and the tuning scans of classical controllers
(the best-gain integrator, the extrapolator's order) on a stream of their own.

:class:`~eofnn.evaluation.experiment.Experiment` runs them; these pieces are also what ``fit`` and ``simulate``
reuse.
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import replace
from typing import Any

from eofnn.analysis.linear import dm_gain_margin
from eofnn.analysis.stability import LoopSetup, analyse_integrator
from eofnn.control.baselines import Integrator
from eofnn.control.config import alpha_past_edge, scan_lqg_settings
from eofnn.control.modal import require_telemetry, within_screen
from eofnn.control.registry import FROM_TELEMETRY, build_controller
from eofnn.data.history import HistorySpec
from eofnn.data.stream import require_target, require_training_memory
from eofnn.errors import CheckpointError, ConfigError, require
from eofnn.evaluation.config import EvaluationConfig, PredictorConfig, with_setting
from eofnn.resources import require_memory, require_time
from eofnn.sim.loop.runner import Controller
from eofnn.sim.scenario import Scenario
from eofnn.training.checkpoint import load_predictor
from eofnn.training.conditions import scenario_conditions, warn_shift
from eofnn.training.fit import FitOutput, FitResult, TrainedPredictor, fit_predictor
from eofnn.training.from_telemetry import fit_from_scenario_telemetry, telemetry_sequences
from eofnn.training.through_loop import loop_work


def fit_from_config(scenario: Scenario, cfg: PredictorConfig, output: FitOutput | None = None) -> FitResult:
    """Train the predictor ``cfg`` describes on telemetry simulated in ``scenario``: against the simulator's truth,
    or (``data.truth: false``) from the telemetry alone, through the plant identified from its dither."""
    margin = dm_gain_margin(scenario.frame_rate_hz) if cfg.optimization.select is not None else None
    fit = fit_predictor if cfg.data.truth else fit_from_scenario_telemetry
    return fit(scenario, cfg.history, cfg.history_length, cfg.network, data=cfg.data, optimization=cfg.optimization,
               output=output, margin=margin)


#: The oracle's reach beyond the contenders' (:func:`oracle_config`): taps more than the longest history, a
#: neighbourhood radius (pitches) wider than the widest (and at least :data:`ORACLE_MIN_RADIUS`), training frames a
#: multiple of the most (and at least :data:`ORACLE_MIN_FRAMES`).
ORACLE_EXTRA_TAPS = 2
ORACLE_EXTRA_RADIUS = 1.0
ORACLE_MIN_RADIUS = 1.5
ORACLE_FRAMES_FACTOR = 4
ORACLE_MIN_FRAMES = 8000


def _radius(cfg: PredictorConfig) -> float:
    """A trained predictor's neighbourhood radius in pitches (0 for a filter that reads one actuator or mode)."""
    network = cfg.network or {}
    args = network.get("init_args") or {}
    return float(args.get("radius", 1.0)) if args.get("structure") == "neighbourhood" else 0.0


def oracle_config(predictors: dict[str, PredictorConfig], scenario: Scenario) -> PredictorConfig:
    """The contest's oracle: the best linear predictor given the true statistics, in the same sensor and loop, as
    far as a least-squares fit finds it. An open-loop (POL) filter over a neighbourhood of actuators, fitted in
    closed form on the simulator's truth: its target is the true future turbulence the loop must cancel (the zonal
    sensor's ``s``; with a Shack-Hartmann the DM's least-squares fit of the true phase, ``data.target: dm_fit``, no
    aliasing), its inputs the measured POL histories, with :data:`ORACLE_EXTRA_TAPS` more taps than the longest
    contender history, a radius :data:`ORACLE_EXTRA_RADIUS` pitch wider than the widest contender's neighbourhood,
    :data:`ORACLE_FRAMES_FACTOR` times the most training frames, and a ridge alpha chosen on validation data
    (``alpha: auto``). It is retrained in each scenario, knows what no telescope knows, and is labelled so
    (``oracle: true``).

    Parameters
    ----------
    predictors : dict
        The contest's controllers (the oracle's reach is set from the predictors it trains).
    scenario : Scenario
        The base scenario (its sensor sets the target).
    """
    from eofnn.data.config import DataConfig
    from eofnn.data.history import MAX_HISTORY_LENGTH
    from eofnn.training.config import OptimizationConfig

    trained = [cfg for cfg in predictors.values() if cfg.trains and not cfg.oracle]
    taps = min(max((cfg.history_length for cfg in trained), default=4) + ORACLE_EXTRA_TAPS, MAX_HISTORY_LENGTH)
    radius = max(max((_radius(cfg) for cfg in trained), default=0.0) + ORACLE_EXTRA_RADIUS, ORACLE_MIN_RADIUS)
    frames = max(ORACLE_FRAMES_FACTOR * max((cfg.data.frames for cfg in trained), default=0), ORACLE_MIN_FRAMES)
    val = max(max((cfg.data.val_frames for cfg in trained), default=0), frames // 8)
    sequence = min(frames, max((cfg.data.sequence_frames for cfg in trained), default=DataConfig.sequence_frames))
    target = "dm_fit" if scenario.sensor.is_shack_hartmann else "measured"
    return PredictorConfig(
        controller="predictor", history="open_loop", history_length=taps,
        network={"class_path": "eofnn.models.linear.LinearFilter",
                 "init_args": {"structure": "neighbourhood", "radius": radius}},
        data=DataConfig(frames=frames, val_frames=val, sequence_frames=sequence, truth=True, target=target),
        optimization=OptimizationConfig(alpha="auto"), oracle=True)


def build_scenarios(base: Scenario, scenarios: dict[str, dict[str, Any]]) -> dict[str, Scenario]:
    """The base scenario with each entry's plant changes (``{}`` is the base plant); ``scenarios`` holds at least
    one, as :func:`~eofnn.evaluation.experiment.predictor_configs` has checked."""
    out = {}
    for name, changes in scenarios.items():
        if changes is not None and not isinstance(changes, dict):
            raise ConfigError(f"scenario {name!r}: {changes!r} is invalid: give a mapping of plant fields, e.g. "
                              "{dm_gain: 2.0}")
        try:
            out[name] = base.with_plant(**(changes or {}))
        except (ConfigError, TypeError) as err:
            raise ConfigError(f"scenario {name!r}: {err}") from None
    return out


def trusted_class_paths(predictors: dict[str, PredictorConfig], extra: Collection[str] = ()) -> set[str]:
    """Network class paths the user named (in the config or on the command line): checkpoints may name these."""
    named = {cfg.network["class_path"] for cfg in predictors.values() if cfg.network is not None}
    return named | set(extra)


def load_configured_checkpoint(name: str, cfg: PredictorConfig, scenarios: dict[str, Scenario],
                               trusted: Collection[str]) -> TrainedPredictor:
    """The checkpoint of controller ``name``, checked against its config (history) and every scenario it runs in."""
    predictor = load_predictor(cfg.checkpoint, trusted_networks=trusted)
    where = f"predictor {name!r}: checkpoint {cfg.checkpoint!r}"
    if cfg.history is not None and cfg.history != predictor.spec.kind:
        raise CheckpointError(f"{where} holds a {predictor.spec.kind} predictor but history={cfg.history!r} was "
                              "asked for")
    for scenario_name, scenario in scenarios.items():
        predictor.check_fits(scenario, f"{where} in scenario {scenario_name!r}", cfg.history_length)
        warn_shift(predictor.info.get("conditions"), scenario_conditions(scenario),
                   f"predictor {name!r} ({cfg.checkpoint}) in scenario {scenario_name!r}")
    return predictor


#: The stream every tuning scan of a classical controller closes its loops on (with seed ``data.seed``): a stream of
#: its own, never the test stream; every setting of one scan sees the same turbulence and noise.
SCAN_STREAM = "gain-scan"


def scan_median_residual(controller: Controller, cfg: PredictorConfig, scenario: Scenario, settle_frames: int,
                         divergence_factor: float) -> float | None:
    """The median residual (nm) of ``controller`` closing the loop on the scan stream: ``cfg.data.frames`` frames
    of seed ``cfg.data.seed``, after ``min(settle_frames, frames // 2)`` frames settle; ``None`` if it diverged."""
    settle = min(settle_frames, cfg.data.frames // 2)
    return scenario.median_residual_nm(controller, cfg.data.frames, cfg.data.seed, SCAN_STREAM, settle,
                                       divergence_factor=divergence_factor)


def scan_settings(cfg: PredictorConfig, settings: list[dict], scenario: Scenario, settle_frames: int,
                  divergence_factor: float, model_of: Callable[[PredictorConfig], Any] | None = None) -> list[dict]:
    """Close the loop on the scan stream with each of ``settings`` (fields of a classical controller's config, e.g.
    ``{"order": 2, "smoothing": 0}``), the controller built from ``cfg`` with those fields replaced, through the
    registry (with ``model_of(config)`` as its model, for a controller built from telemetry): each setting with its
    ``median_rms_nm`` (``None`` where the loop diverged), in the order given."""
    entries = []
    for setting in settings:
        setting_cfg = with_setting(cfg, setting)
        controller = build_controller(setting_cfg, None if model_of is None else model_of(setting_cfg))
        entries.append({**setting, "median_rms_nm": scan_median_residual(controller, cfg, scenario, settle_frames,
                                                                         divergence_factor)})
    return entries


#: The config fields that ask for a scan of a classical controller's settings (``setting_grid``).
SCAN_FIELDS = ("orders", "smoothings", "ar_orders", "noise_scales", "pfc_alphas")


def scan_classical_settings(cfg: PredictorConfig, scenario: Scenario, settle_frames: int,
                            divergence_factor: float) -> tuple[dict, Any]:
    """A classical controller's settings tuned like the integrator's gain (the extrapolator's order and smoothing,
    the LQG's AR order and noise scale, PFC's memory): each of ``cfg.setting_grid`` closes the loop on the scan stream,
    and the lowest median residual wins (the first tried on a tie); PFC's memory and the LQG's noise scale are scanned
    on past the grid's edge while the best is there (:func:`~eofnn.control.config.alpha_past_edge`,
    :func:`~eofnn.control.config.scan_lqg_settings`). A controller built from telemetry builds one model per setting, each
    from the same telemetry (its own streams: neither the scan's nor the test's).

    Returns the scan, ``{**chosen setting, "median_rms_nm": its residual, "scanned": every setting tried with its
    residual}``, and the chosen setting's model (``None`` for a controller without one)."""
    from_telemetry = FROM_TELEMETRY.get(cfg.controller)
    models: list[Any] = []

    def model_of(setting_cfg: PredictorConfig) -> Any:
        models.append(from_telemetry(setting_cfg, scenario))
        return models[-1]

    plain = replace(cfg, **dict.fromkeys(SCAN_FIELDS))
    if cfg.controller == "lqg":  # every model with every noise scale, the scales on past their edge
        def evaluate(order: int, scale: float) -> float | None:
            scanned.extend(scan_settings(plain, [{"ar_order": order, "noise_scale": scale}], scenario, settle_frames,
                                         divergence_factor, model_of))
            return scanned[-1]["median_rms_nm"]

        scanned: list[dict] = []
        grid = cfg.setting_grid
        scan_lqg_settings(evaluate, [s["ar_order"] for s in grid], [s["noise_scale"] for s in grid])
    else:
        scanned = scan_settings(plain, cfg.setting_grid, scenario, settle_frames, divergence_factor,
                                model_of if from_telemetry is not None else None)
    # PFC's memory, like the integrator's gain, goes on past the grid's edge while the residual still falls there.
    while cfg.pfc_alphas is not None and (alpha := alpha_past_edge(
            {e["pfc.alpha"]: e["median_rms_nm"] for e in scanned}, len(scanned) - len(cfg.setting_grid))) is not None:
        scanned += scan_settings(plain, [{"pfc.alpha": alpha}], scenario, settle_frames, divergence_factor,
                                 model_of if from_telemetry is not None else None)
    finite = [i for i, entry in enumerate(scanned) if entry["median_rms_nm"] is not None]
    asked = ", ".join(f"{name}={getattr(cfg, name)!r}" for name in SCAN_FIELDS if getattr(cfg, name) is not None)
    require(bool(finite), f"every setting of controller {cfg.controller} ({asked}) diverged: check the plant's DM "
                          "gain against dm_gain_model")
    best = min(finite, key=lambda i: scanned[i]["median_rms_nm"])
    chosen = {key: value for key, value in scanned[best].items() if key != "median_rms_nm"}
    scan = {**chosen, "median_rms_nm": scanned[best]["median_rms_nm"], "scanned": scanned}
    return scan, (models[best] if models else None)


#: The most rounds of refinement of a best-gain integrator's scan (while the best is still the highest gain
#: tried, climbing towards the critical gain).
MAX_REFINE_ROUNDS = 6


def scan_integrator_gains(cfg: PredictorConfig, scenario: Scenario, settle_frames: int,
                          divergence_factor: float) -> dict:
    """Close the loop with each of ``cfg.gains`` on a stream of its own; the lowest median residual wins, after
    ``cfg.refine_rounds`` rounds of refinement between the best gain and its neighbours (past the grid's top
    up to the analytic critical gain, below its bottom down to 0), so the choice is never an edge of the grid
    unless it is the edge of what is stable (then ``at_edge`` says so)."""
    # The critical integrator gain: the loop gain at which an integrator goes unstable in a nominal plant of
    # this delay (a small gain's DM-gain margin times that gain), over this plant's DM and WFS gains.
    nominal = LoopSetup(scenario.plant.delay_frames, frame_rate_hz=scenario.frame_rate_hz)
    critical = (0.01 * float(analyse_integrator(0.01, cfg.leak, nominal).gain_margin[1])
                / (scenario.plant.dm_gain * scenario.plant.wfs_gain))
    scanned: dict[float, float | None] = {}

    def run(gain: float) -> None:
        scanned[gain] = scan_median_residual(Integrator(gain, cfg.leak), cfg, scenario, settle_frames,
                                             divergence_factor)

    for gain in cfg.gains:
        run(gain)
    require(any(v is not None for v in scanned.values()),
            f"every integrator gain of gains={cfg.gains!r} diverged: give smaller gains")
    refined = []
    for round_index in range(MAX_REFINE_ROUNDS if cfg.refine_rounds else 0):
        gains = sorted(scanned)
        best = min((rms, g) for g, rms in scanned.items() if rms is not None)[1]
        i = gains.index(best)
        top = i + 1 == len(gains)
        if round_index >= cfg.refine_rounds and not (top and best < 0.98 * critical):
            break  # refined enough, and not still climbing towards the critical gain
        left = gains[i - 1] if i > 0 else 0.0
        right = min(gains[i + 1] if not top else critical, 0.99 * critical)
        for candidate in ((left + best) / 2, (best + right) / 2):
            candidate = float(f"{candidate:.4g}")
            if candidate > 0 and candidate not in scanned and candidate < critical:
                run(candidate)
                refined.append(candidate)
    finite = sorted((rms, g) for g, rms in scanned.items() if rms is not None)
    best = finite[0][1]
    gains = sorted(scanned)
    at_edge = best == gains[0] or (best == gains[-1] and best < 0.98 * critical)
    return {"gain": best, "scanned": {f"{g:g}": scanned[g] for g in gains}, "refined": refined,
            "critical_gain": critical, "at_edge": at_edge}


def check_experiment(scenarios: dict[str, Scenario], predictors: dict[str, PredictorConfig],
                     evaluation: EvaluationConfig, trusted_networks: Collection[str] = (), allow_long: bool = False
                     ) -> dict[str, TrainedPredictor]:
    """Everything an experiment can refuse before it runs: memory of the evaluation and of each training stream, its
    estimated time, the streams the turbulence screens must hold, ``train_in`` names, and the checkpoints (loaded and
    checked against every scenario: returned by controller name)."""
    n_act = max(s.grid.n_actuators for s in scenarios.values())
    # Per frame and realisation two RMS values are kept; per realisation a turbulence chunk of 1024 frames
    # and the arrays of that chunk (s, y, eps, wfs) are in flight.
    require_memory(8 * evaluation.realisations * (2 * evaluation.frames + 5 * 1024 * n_act),
                   f"evaluation with evaluation.frames={evaluation.frames}, evaluation.realisations="
                   f"{evaluation.realisations} and {n_act} actuators")
    trusted = trusted_class_paths(predictors, trusted_networks)
    loaded: dict[str, TrainedPredictor] = {}
    for name, cfg in predictors.items():
        if cfg.trains:
            for scenario_value in scenarios.values():
                spec = HistorySpec.from_scenario(cfg.history, cfg.history_length, scenario_value)
                require_training_memory(scenario_value, spec, cfg.data)
                require_target(scenario_value, cfg.data)
        if cfg.train_in is not None and cfg.train_in not in scenarios:
            raise ConfigError(f"predictor {name!r}: train_in={cfg.train_in!r} is not a scenario: allowed are "
                              f"{', '.join(scenarios)}")
        if cfg.checkpoint is not None:
            loaded[name] = load_configured_checkpoint(name, cfg, scenarios, trusted)
    # Time: every controller runs in every scenario; each trained predictor simulates its data once per scenario
    # (or once where train_in says).
    work = evaluation.frames * evaluation.realisations * n_act * len(predictors) * len(scenarios)
    work += sum(len(cfg.gains) * cfg.data.frames * n_act * len(scenarios)
                for cfg in predictors.values() if cfg.gains is not None)
    work += sum(len(cfg.setting_grid) * cfg.data.frames * n_act * len(scenarios)
                for cfg in predictors.values() if cfg.setting_grid is not None)
    work += sum((cfg.data.realisations * (cfg.data.frames + cfg.data.val_frames) * (cfg.data.refit_rounds + 1) * n_act
                 + loop_work(cfg.optimization, cfg.data, n_act)) * (1 if cfg.train_in else len(scenarios))
                for cfg in predictors.values() if cfg.trains)
    require_time(work, f"this experiment ({len(predictors)} controllers x {len(scenarios)} scenarios, "
                 f"{n_act} actuators)", allow_long)
    # Streams the exact turbulence screen must hold (training sequences are checked with their memory).
    for scenario_name, scenario_value in scenarios.items():
        scenario_value.require_stream_frames(evaluation.frames, f"evaluation.frames={evaluation.frames}",
                                             evaluation.realisations)
        scenario_value.require_changes_within(evaluation.frames, f"scenario {scenario_name!r}")
        for name, cfg in predictors.items():
            if cfg.gains is not None or cfg.setting_grid is not None:
                what = "the gain scan" if cfg.gains is not None else "the scan of its settings"
                scenario_value.require_stream_frames(cfg.data.frames, f"predictor {name!r}: data.frames="
                                                     f"{cfg.data.frames} ({what})")
            if cfg.controller in FROM_TELEMETRY:  # (an LQG whose AR order is scanned checks both)
                require_telemetry(cfg.data, scenario_value.grid.n_actuators, cfg.modes, f"predictor {name!r}")
                data, _ = within_screen(scenario_value, cfg.data)  # split into realisations that fit the screen
                scenario_value.require_stream_frames(data.frames, f"predictor {name!r}: data.frames="
                                                     f"{data.frames} (its telemetry)", data.realisations)
            elif cfg.trains and not cfg.data.truth:
                n_sequences, n, _ = telemetry_sequences(cfg.data)
                scenario_value.require_stream_frames(n, f"predictor {name!r}: telemetry training ({n_sequences} "
                                                     f"sequence(s) of {n} frames, data.sequence_frames="
                                                     f"{cfg.data.sequence_frames})",
                                                     n_sequences * cfg.data.realisations)
    return loaded
