"""Training from telemetry alone: a predictor fitted on recorded ``y`` and ``wfs`` through an identified plant.

The simulator-truth path (:func:`eofnn.training.fit.fit_predictor`) learns ``-s(n)/g`` with the true ``s`` and
``g``; this one learns ``-s_hat(n)/g_hat`` with ``s_hat = wfs - DM_model(y)`` and ``DM_model``, ``g_hat`` from
:func:`eofnn.training.identify.identify_plant` (or a plant given by the user, or the nominal assumption ``DM(y) = y``,
which is what the study's open-loop EOF does and why it fails under a DM gain error).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import torch
from torch import nn

from eofnn.control.baselines import record_dithered
from eofnn.data.history import HistorySpec
from eofnn.data.stream import DataConfig
from eofnn.data.targets import AnyTelemetry, TelemetryBatches, check_sequences, telemetry_grid, telemetry_items
from eofnn.errors import ConfigError, TelemetryError
from eofnn.resources import require_memory
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.layout import ActuatorLayout, dm_model, layout_to_dict
from eofnn.sim.loop.plant import Plant, PlantModel
from eofnn.sim.scenario import Scenario
from eofnn.training.alpha import MarginFunction
from eofnn.training.conditions import Conditions, plant_conditions, scenario_conditions
from eofnn.training.fit import DEFAULT_NETWORK, FitData, FitOutput, FitResult, bind_margin, new_task, solve
from eofnn.training.identify import IdentifiedPlant, identify_plant
from eofnn.training.task import OptimizationConfig


@dataclass
class TelemetryDataConfig:
    """How recorded telemetry is read and split for a fit.

    Parameters
    ----------
    batch_frames : int
        Frames per streamed batch.
    val_frames : int
        The last ``val_frames`` frames (before ``stop``) of each sequence are held out as validation.
    stop : int, optional
        Train on frames before ``stop`` only (keep the rest for :func:`eofnn.evaluation.replay.replay`).
    seed : int
        Seed of network initialisation and SGD.
    target : {"measured", "s"}
        What the targets cancel: the measured POL values (telemetry alone), or the telemetry's ``s`` array, a
        simulator's truth recorded beside it (:class:`~eofnn.data.targets.TelemetryBatches`).
    target_dm_gain : float, optional
        The DM gain of ``"s"`` targets (the simulator's DM); default the plant's.
    """

    batch_frames: int = 1024
    val_frames: int = 0
    stop: int | None = None
    seed: int = 0
    target: str = "measured"
    target_dm_gain: float | None = None

    @classmethod
    def of(cls, data: DataConfig, val_frames: int) -> TelemetryDataConfig:
        """The telemetry twin of a predictor's ``data`` (its batches and seed), holding out ``val_frames``."""
        return cls(data.batch_frames, val_frames, seed=data.seed)


def resolve_plant(plant: IdentifiedPlant | dict | None, delay_frames: int | float,
                  grid: ActuatorGrid | ActuatorLayout | None):
    """``(dm_response, dm_gain, model_errors, source)`` of an identified plant, model errors, or the nominal DM."""
    if isinstance(plant, IdentifiedPlant):
        return plant.dm_response("model"), float(plant.dm_gain or 0.0), plant.model_errors(), "identified"
    errors = dict(plant or {})
    model = Plant(delay_frames=delay_frames).with_errors(**errors)
    if model.misregistration_x or model.misregistration_y:
        if isinstance(grid, ActuatorGrid):
            return PlantModel(model, grid).apply_dm, model.dm_gain, errors, "given"
        return dm_model(grid, model.dm_gain, model.misregistration_x, model.misregistration_y), model.dm_gain, \
            errors, "given"
    return (lambda y: model.dm_gain * y), model.dm_gain, errors, "given" if errors else "nominal"


def fit_from_telemetry(telemetry: AnyTelemetry | Sequence[AnyTelemetry], spec: HistorySpec, network: dict | None = None,
                       *, plant: IdentifiedPlant | dict | None = None, grid: ActuatorGrid | None = None,
                       data: TelemetryDataConfig | None = None, optimization: OptimizationConfig | None = None,
                       output: FitOutput | None = None, info: dict | None = None,
                       margin: MarginFunction | None = None) -> FitResult:
    """Train a predictor on telemetry alone (the telemetry twin of :func:`eofnn.training.fit.fit_predictor`).

    Parameters
    ----------
    telemetry : Telemetry, StreamedTelemetry or a sequence of them
        Recorded ``y`` and ``wfs`` (nm): one or several files, batched or not. A
        :class:`~eofnn.telemetry.file.StreamedTelemetry` is read ``data.batch_frames`` frames at a time (plus the
        history's overlap), so the fit never holds the file: memory is set by ``batch_frames``, the actuators and the
        network's normal equations (refused up front when that does not fit).
    spec : HistorySpec
        History kind, length and delay (the delay must be the telemetry's).
    network : dict, optional
        ``{"class_path": ..., "init_args": {...}}``; a per-actuator linear filter (the study's EOF) by default.
    plant : IdentifiedPlant, dict or None
        The DM model for POL values and targets: an identification result, a dict of model errors
        (``dm_gain``, ``misregistration_x``, ``misregistration_y``), or None for the nominal ``DM(y) = y``.
    grid : ActuatorGrid or ActuatorLayout, optional
        The actuator layout, when the telemetry holds no positions (neighbourhood filters and misregistered DM models
        need it).
    data : TelemetryDataConfig
        Batches, the validation frames held out, the last frame trained on, and the seed.
    optimization : OptimizationConfig
        Closed form (linear networks, one streamed pass) or SGD (any network, e.g. the MLP).
    output : FitOutput
        Where to write a checkpoint that :func:`eofnn.training.checkpoint.load_predictor` reads, and the progress bar.
    info : dict, optional
        Provenance recorded in the checkpoint (e.g. the telemetry files).
    margin : callable, optional
        :data:`~eofnn.training.alpha.MarginFunction`, for an ``optimization.select`` constraint (checked in the
        loop the fit believes in: the identified or given DM gain).
    """
    optimization = optimization or OptimizationConfig()
    if optimization.fit_method == "closed_loop":
        raise ConfigError("optimization.fit_method: closed_loop trains through the simulated loop: it needs a "
                          "scenario and simulator truth, not telemetry alone (use closed_form or sgd)")
    sequences = check_sequences(telemetry, spec)
    data = data or TelemetryDataConfig()
    output = (output or FitOutput()).checked()
    n_act, n_frames = sequences[0].y.shape[-1], min(seq.y.shape[0] for seq in sequences)
    first_item = telemetry_items(telemetry)[0]
    grid = telemetry_grid(first_item, grid)
    dm_response, dm_gain, errors, source = resolve_plant(plant, spec.delay_frames, grid)
    stop, val_frames, batch_frames = data.stop, data.val_frames, data.batch_frames
    train_stop = (stop if stop is not None else n_frames) - val_frames
    span = spec.first_frame + spec.target_lead
    if train_stop <= span or (val_frames and val_frames <= span):
        raise TelemetryError(f"stop={stop}, val_frames={val_frames}: {n_frames} frames leave no training or "
                             f"validation history (each needs more than {span} frames)")
    conditions = plant_conditions(plant if plant is not None else {}, f"plant {source} from the telemetry"
                                  if source == "identified" else f"{source} plant")
    info = {"targets": "telemetry" if data.target == "measured" else "telemetry's s (simulator truth)",
            "plant_source": source, "model_errors": errors, "dm_gain_model": dm_gain,
            "n_sequences": len(sequences), "conditions": conditions.to_dict(), **(info or {})}
    if first_item.modal_basis is not None:  # a modal predictor: actuator commands are modal_basis @ y
        info["modal_basis_shape"] = list(first_item.modal_basis.shape)
    if first_item.measurement:
        info["measurement"] = first_item.measurement
    task = new_task(network or DEFAULT_NETWORK, n_act, spec, None if grid is None else layout_to_dict(grid),
                    optimization, info, data.seed)
    require_memory(fit_working_bytes(task.network, spec, n_act, batch_frames),
                   f"fitting from telemetry ({n_act} actuators, {spec.n_taps} taps, batches of {batch_frames} frames)")
    targets = {"target": data.target, "target_dm_gain": data.target_dm_gain}
    train = TelemetryBatches(sequences, spec, dm_response, dm_gain, batch_frames, stop=train_stop, **targets)
    val = TelemetryBatches(sequences, spec, dm_response, dm_gain, batch_frames, first=train_stop,
                           stop=train_stop + val_frames, **targets) if val_frames else None
    if val is None and optimization.fit_method == "closed_form" and optimization.alpha_for(False) == "auto":
        raise ConfigError("optimization.alpha: auto chooses alpha on held-out telemetry: give val_frames > 0 "
                          "(or a fixed optimization.alpha)")
    if val is None and optimization.search is not None:
        raise ConfigError("optimization.search chooses on held-out telemetry: give val_frames > 0")
    solved = solve(task, FitData(train, val, train_stop * len(sequences)), optimization, output=output, seed=data.seed,
                   margin=bind_margin(margin, task.network, spec, dm_gain or 1.0, dm_gain or 1.0))
    return solved.result(output)


def fit_working_bytes(network: nn.Module, spec: HistorySpec, n_act: int, batch_frames: int) -> int:
    """Bytes a streamed fit holds at once, whatever the length of the telemetry: one window of ``y`` and ``wfs``
    (read buffer and float64), its POL values, the batch's history and targets, the network's features of them
    (closed form: with their float64 copy), and the normal equations (sized from the network's features of one
    sample)."""
    window = (batch_frames + spec.first_frame + spec.target_lead) * n_act * 8
    history = batch_frames * n_act * spec.n_taps * 8
    equations = 0
    if hasattr(network, "features"):
        with torch.no_grad():
            groups, _, n_features = network.features(
                torch.zeros(1, n_act, spec.n_taps, dtype=network.weight.dtype)).shape
        history = max(history, batch_frames * groups * n_features * 8)
        equations = groups * (n_features + 2) ** 2 * 8
    return 4 * window + 4 * history + equations


def telemetry_sequences(data: DataConfig) -> tuple[int, int, int]:
    """``(sequences, frames per sequence, validation frames per sequence)`` of telemetry recorded for training.

    Like the simulator-truth streams, telemetry longer than ``data.sequence_frames`` is recorded as several
    independent sequences (an observatory's separate telemetry runs, each on its own turbulence realisation): one
    turbulence screen need not hold ``frames + val_frames``, and each sequence holds out its own last
    ``ceil(val_frames / sequences)`` frames. Up to ``data.sequence_frames``, one sequence, as before.
    """
    total = data.frames + data.val_frames
    n_sequences = max(1, -(-total // data.sequence_frames))
    val_frames = -(-data.val_frames // n_sequences)
    return n_sequences, -(-data.frames // n_sequences) + val_frames, val_frames


def fit_from_scenario_telemetry(scenario: Scenario, history: str = "open_loop", history_length: int = 4,
                                network: dict | None = None, *, data: DataConfig | None = None,
                                optimization: OptimizationConfig | None = None, output: FitOutput | None = None,
                                margin: MarginFunction | None = None) -> FitResult:
    """What an observatory would do in ``scenario``: record telemetry, identify the plant, fit from telemetry alone.

    The telemetry twin of :func:`eofnn.training.fit.fit_predictor` for studies (``compare`` with a predictor that
    does not learn from simulator truth): ``data.frames + data.val_frames`` frames per realisation are recorded
    (in independent sequences of at most ``data.sequence_frames``, as the simulator-truth path streams them; see
    :func:`telemetry_sequences`) with an integrator (``data.integrator_gain``) plus ``data.dither_nm`` of white
    dither in the scenario's plant; the plant is identified from that dither, and the predictor is fitted from
    ``y`` and ``wfs`` alone, the last
    ``data.val_frames`` frames (split evenly over the sequences) held out for validation. The learner never sees
    ``s`` or the plant.
    """
    data = data or DataConfig()
    output = output or FitOutput()
    spec = HistorySpec.from_scenario(history, history_length, scenario)
    if data.dither_nm <= 0:
        raise ConfigError(f"data.dither_nm={data.dither_nm!r} is invalid for telemetry training: the plant is "
                          "identified from the dither, so it must be > 0 (nm)")
    n_sequences, n_frames, val_frames = telemetry_sequences(data)
    scenario.require_stream_frames(n_frames, f"telemetry training ({n_sequences} sequence(s) of {n_frames} frames)")
    streams = ("telemetry-train", "telemetry-dither", "telemetry-noise")
    result = record_dithered(scenario, data, n_frames, streams, n_sequences * data.realisations,
                             progress=output.progress, where=" in the scenario's plant")
    plant = identify_plant(result.telemetry)
    plant.require_identified()
    return fit_from_telemetry(result.telemetry, spec, network, plant=plant,
                              data=TelemetryDataConfig.of(data, val_frames), optimization=optimization,
                              output=output, margin=margin, info={"scenario": scenario.to_dict(), "data": asdict(data),
                                    "identified_plant": plant.model_errors(), "conditions": Conditions(
                                        plant.wfs_noise_nm, plant.dm_gain,
                                        scenario_conditions(scenario).wind_speeds_mps,
                                        "plant identified from the scenario's telemetry").to_dict()})
