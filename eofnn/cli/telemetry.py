"""``eofnn identify``, ``eofnn replay``, ``eofnn export``, and the telemetry path of ``eofnn fit``: from recorded
telemetry alone (``docs/telemetry.md``) to a deployable filter (``docs/export.md``)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import eofnn
from eofnn.cli.common import Output, TelemetryCommand, log
from eofnn.errors import CheckpointError, ConfigError, TelemetryError
from eofnn.outputs import check_output_file, check_output_folder, staged_folder
from eofnn.telemetry.units import check_units
from eofnn.training.conditions import plant_conditions, warn_shift
from eofnn.validation import Interval, OrNone, check_value

# What the commands run imports torch & co. (seconds): imported in the functions, so that the parsers of identify,
# replay, export and fit (built from the dataclasses below) and their config errors answer without it.
# Annotations name heavy types by their module path (``import eofnn``), never in a TYPE_CHECKING block: jsonargparse
# runs a config module's TYPE_CHECKING imports when it reads the config's types, which would import torch & co.

IDENTIFY = ("Identify the plant from dithered closed-loop telemetry (FITS/npz with y and wfs, docs/telemetry.md): DM "
            "gain, per-actuator gains, misregistration and neighbour coupling, WFS lag and noise (with "
            "--optical_gain_modes: per-mode gains, a pyramid's optical gains), each with a standard error, into "
            "plant.json.")
REPLAY = ("Replay a checkpoint on held-out telemetry: its prediction error against what the telemetry later shows "
          "was needed (RMS per frame, map per actuator, temporal PSD), beside the telemetry's own controller, into "
          "DIR/replay.json and DIR/replay.png.")
EXPORT = ("Export a linear predictor's coefficients as FITS (docs/export.md) for eofnn.runtime.PredictiveFilter or any "
          "other real-time computer.")
PLANT_HELP = ("DM model for POL values and targets: 'identify' (from this telemetry's dither), 'nominal' (DM(y) = y: "
              "the study's assumption) or a plant.json written by eofnn identify.")


MATRICES = ("interaction_matrix", "reconstructor", "modal_basis")


def resolve_plant_option(plant: str, telemetry: list[eofnn.data.targets.AnyTelemetry],
                         ) -> eofnn.training.identify.IdentifiedPlant | None:
    """``--plant``: identify from the telemetry, the nominal DM (None), or a plant.json."""
    from eofnn.training.identify import IdentifiedPlant, identify_plant

    if plant == "identify":
        identified = identify_plant(telemetry)
        identified.require_identified()
        return identified
    if plant == "nominal":
        return None
    identified = IdentifiedPlant.from_json(plant)
    n_act, delay = telemetry[0].y.shape[-1], telemetry[0].delay_frames
    if identified.actuator_gains and len(identified.actuator_gains) != n_act:
        raise TelemetryError(f"plant={plant!r} was identified for {len(identified.actuator_gains)} actuators but the "
                             f"telemetry has {n_act}: identify the plant on telemetry of this system")
    if identified.delay_frames != delay:
        raise TelemetryError(f"plant={plant!r} was identified with delay_frames={identified.delay_frames} but the "
                             f"telemetry has delay_frames={delay}")
    return identified


def check_checkpoint_fits(predictor, checkpoint: str, telemetry: list[eofnn.data.targets.AnyTelemetry]) -> None:
    """One line unless the checkpoint's network runs on this telemetry (actuators, delay)."""
    n_act, delay = telemetry[0].y.shape[-1], telemetry[0].delay_frames
    if predictor.n_actuators != n_act:
        raise CheckpointError(f"checkpoint {checkpoint!r} was trained for {predictor.n_actuators} actuators but the "
                              f"telemetry has {n_act}")
    if predictor.spec.delay_frames != delay:
        raise CheckpointError(f"checkpoint {checkpoint!r} was trained for delay_frames={predictor.spec.delay_frames} "
                              f"but the telemetry has delay_frames={delay}")


@dataclass(kw_only=True)
class IdentifyConfig(TelemetryCommand):
    """``eofnn identify``: the plant from dithered telemetry.

    Parameters
    ----------
    out : str
        plant.json to write.
    radius : float
        Coupling neighbourhood radius in pitches.
    nuisance_lags : int
        Past frames of y and wfs as nuisance regressors.
    max_lag : int, optional
        Largest WFS lag searched (frames).
    batch_frames : int
        Frames read and regressed at a time (memory: about 8 bytes x actuators x batch_frames x (neighbours + 2
        nuisance_lags + 8), whatever the length of the file).
    optical_gain_modes : list of int
        Karhunen-Loeve command modes (1-based orders) whose gains (the DM gain times the sensor's optical gain, a
        pyramid's optical gains) are identified from a dither on them, each with a standard error (docs/telemetry.md).
    """

    radius: float = 1.5
    nuisance_lags: int = 2
    max_lag: int | None = None
    batch_frames: int = 1024
    optical_gain_modes: list[int] = field(default_factory=list)


def _files(value: str | list[str]) -> list[str]:
    return [value] if isinstance(value, str) else list(value)


def _load(cfg, streamed: bool = False) -> list[eofnn.data.targets.AnyTelemetry]:
    """Read the telemetry files (with matrices given beside them) and say how each residual was formed when it was
    not recorded as one. ``streamed``: open them for block reading (identification and fits never hold a file)."""
    from eofnn.data.targets import in_nm, load_telemetry

    paths = cfg.telemetry
    check_units(cfg.command_unit, cfg.measurement_unit)
    telemetry = load_telemetry(paths, {name: getattr(cfg, name, None) for name in MATRICES}, streamed=streamed)
    for index, (path, item) in enumerate(zip(_files(paths), telemetry, strict=True)):
        telemetry[index], note = in_nm(item, cfg.command_unit, cfg.measurement_unit)
        if note:
            log(f"telemetry {path}: {note}")
        if item.measurement:
            log(f"telemetry {path}: {item.measurement}")
        if item.modal_basis is not None:
            log(f"telemetry {path}: modal, {item.y.shape[-1]} modes of a {tuple(item.modal_basis.shape)} basis: "
                "predictors run in modes, actuator commands are modal_basis @ y")
    return telemetry


def identify(cfg: IdentifyConfig, config_dump: str | None = None) -> dict:
    """Identify the plant from ``cfg.telemetry`` and write it to ``cfg.out``; returns the summary line."""
    check_value("batch_frames", cfg.batch_frames, Interval(1, 1_000_000, integer=True, unit="frames"))
    check_units(cfg.command_unit, cfg.measurement_unit)
    out = check_output_file(cfg.out, cfg.overwrite)
    from eofnn.training.identify import IdentifiedPlant, identify_plant

    telemetry = _load(cfg, streamed=True)
    try:
        plant = identify_plant(telemetry, radius=cfg.radius, nuisance_lags=cfg.nuisance_lags, max_lag=cfg.max_lag,
                               batch_frames=cfg.batch_frames)
    except TelemetryError as err:  # a dither on a few modes only: their gains, not the DM response, are identified
        if not cfg.optical_gain_modes:
            raise
        plant = IdentifiedPlant(False, telemetry[0].delay_frames, {}, n_frames=sum(t.y.shape[0] for t in telemetry),
                                warnings=[f"the DM response was not identified ({err})"])
    if cfg.optical_gain_modes:
        from eofnn.training.modal_gains import identify_modal_gains

        plant.optical_gains = identify_modal_gains(telemetry, cfg.optical_gain_modes, lag_frames=plant.lag_frames or 0,
                                                   nuisance_lags=cfg.nuisance_lags, batch_frames=cfg.batch_frames)
    plant.settings["telemetry"] = _files(cfg.telemetry)
    plant.to_json(out, overwrite=cfg.overwrite)
    keys = ("identified", "dm_gain", "dm_gain_se", "misregistration_x", "misregistration_x_se", "misregistration_y",
            "misregistration_y_se", "lag_frames", "wfs_noise_nm", "wfs_noise_nm_se")
    summary = {"plant": str(out), **{k: getattr(plant, k) for k in keys}}
    if plant.optical_gains:
        summary["optical_gains"] = {k: plant.optical_gains[k] for k in ("orders", "gains", "gains_se")}
    for warning in plant.warnings if plant.identified or plant.optical_gains else []:  # undithered: warned already
        log(f"identify: {warning}")
    log(json.dumps(summary))
    return summary


def fit_telemetry(cfg, out: Path) -> eofnn.training.fit.FitResult:
    """The telemetry path of ``eofnn fit`` (``cfg``: its :class:`~eofnn.cli.fit.FitConfig`)."""
    from eofnn.analysis.linear import dm_gain_margin
    from eofnn.data.history import HistorySpec
    from eofnn.training.fit import FitOutput
    from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry

    p = cfg.predictor  # a PredictorConfig
    telemetry = _load(cfg, streamed=True)  # read predictor.data.batch_frames frames at a time, never whole
    spec = HistorySpec(p.history, p.history_length, telemetry[0].delay_frames)
    plant = resolve_plant_option(cfg.plant, telemetry)
    frames = min(seq.y.shape[0] for t in telemetry for seq in t.sequences())
    log(f"fitting {p.history} predictor, history {p.history_length}, {p.optimization.fit_method}, from telemetry "
        f"{', '.join(_files(cfg.telemetry))} ({frames} frames), plant {cfg.plant}")
    return fit_from_telemetry(telemetry, spec, p.network, plant=plant,
                              data=TelemetryDataConfig.of(p.data, min(p.data.val_frames, frames // 5)),
                              optimization=p.optimization, output=FitOutput(out, cfg.overwrite, bool(cfg.progress)),
                              info={"telemetry": _files(cfg.telemetry)},
                              margin=dm_gain_margin() if p.optimization.select is not None else None)


@dataclass(kw_only=True)
class ReplayConfig(TelemetryCommand):
    """``eofnn replay``: a checkpoint on held-out telemetry.

    Parameters
    ----------
    out : str
        Folder for replay.json and replay.png.
    checkpoint : str
        Predictor checkpoint (eofnn fit).
    plant : str
        {plant_help}
    start : int
        First frame of each file to replay (earlier: history).
    settle_frames : int
        Frames after the first left out of statistics.
    trusted_networks : list of str
        Network class paths, beyond eofnn's own, that the checkpoint may name.
    """

    checkpoint: str
    plant: str = "identify"
    start: int = 0
    settle_frames: int = 0
    trusted_networks: list[str] = field(default_factory=list)


ReplayConfig.__doc__ = ReplayConfig.__doc__.replace("{plant_help}", PLANT_HELP)


def replay(cfg: ReplayConfig, config_dump: str | None = None) -> dict:
    """Replay ``cfg.checkpoint`` on ``cfg.telemetry`` and write ``replay.json`` and ``replay.png`` into ``cfg.out``;
    returns the summary line."""
    check_value("start", cfg.start, Interval(0, 10**9, integer=True))
    check_value("settle_frames", cfg.settle_frames, Interval(0, 10**9, integer=True))
    check_units(cfg.command_unit, cfg.measurement_unit)
    out = check_output_folder(cfg.out, cfg.overwrite)
    from eofnn.data.targets import telemetry_grid
    from eofnn.evaluation.replay import replay as replay_telemetry
    from eofnn.reporting.replay import replay_figure
    from eofnn.training.checkpoint import load_predictor

    predictor = load_predictor(cfg.checkpoint, trusted_networks=cfg.trusted_networks)
    telemetry = _load(cfg, streamed=True)  # replayed in blocks of frames, never whole
    check_checkpoint_fits(predictor, cfg.checkpoint, telemetry)
    plant = resolve_plant_option(cfg.plant, telemetry)
    # Noise and DM gain of this telemetry against the checkpoint's training (a nominal plant knows no noise).
    shift = [] if plant is None else warn_shift(
        predictor.info.get("conditions"),
        plant_conditions(plant, "identified from this telemetry" if cfg.plant == "identify" else f"plant {cfg.plant}"),
        f"replay of {cfg.checkpoint}")
    result = replay_telemetry(predictor.network, predictor.spec, telemetry, plant=plant, start=cfg.start,
                    settle_frames=cfg.settle_frames)
    result.shift = shift
    result.guard["checkpoint_sha256"] = _sha256(cfg.checkpoint)
    with staged_folder(out, cfg.overwrite) as folder:
        result.to_json(folder / "replay.json")
        replay_figure(result, folder / "replay.png", telemetry_grid(telemetry[0]))
    summary = {"replay": str(out / "replay.json"), **result.summary()}
    log(json.dumps(summary))
    return summary


@dataclass(kw_only=True)
class ExportConfig(Output):
    """``eofnn export``: a linear predictor's filter for a real-time computer.

    Parameters
    ----------
    checkpoint : str
        Linear predictor checkpoint (eofnn fit).
    out : str
        Filter FITS file to write.
    dm_gain_model : float, optional
        DM gain of the POL reconstruction (open loop); default the one the fit used, else 1.
    guard : str, optional
        replay.json of eofnn replay of this checkpoint on the user's telemetry: the filter is exported only if that
        guard deployed the predictor.
    """

    checkpoint: str
    dm_gain_model: float | None = None
    guard: str | None = None


def _sha256(path: str) -> str:
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _check_guard(guard_file: str, checkpoint: str) -> dict:
    """The guard's decision in ``guard_file``; one line unless it deployed this very checkpoint."""
    try:
        guard = json.loads(Path(guard_file).read_text()).get("guard") or {}
    except (OSError, ValueError, AttributeError) as err:
        raise ConfigError(f"guard={guard_file!r} is not a replay.json of eofnn replay: {err}") from None
    if guard.get("checkpoint_sha256") != _sha256(checkpoint):
        raise ConfigError(f"guard={guard_file!r} did not replay checkpoint {checkpoint!r}: run eofnn replay on it")
    if guard.get("deployed") != "predictor":
        raise ConfigError(f"guard={guard_file!r} kept the telemetry's own controller ({guard.get('why')}): nothing "
                          "exported")
    return guard


def export(cfg: ExportConfig, config_dump: str | None = None) -> dict:
    """Write ``cfg.checkpoint``'s filter as FITS to ``cfg.out``; returns the summary line."""
    check_value("dm_gain_model", cfg.dm_gain_model, OrNone(Interval(0, 100, closed="right")))
    out = check_output_file(cfg.out, cfg.overwrite)
    guard = _check_guard(cfg.guard, cfg.checkpoint) if cfg.guard else None
    from eofnn.control.predictive import believed_dm_gain
    from eofnn.training.checkpoint import load_predictor
    from eofnn.training.export import export_filter

    predictor = load_predictor(cfg.checkpoint)
    gain = believed_dm_gain(cfg.dm_gain_model, predictor)
    try:
        export_filter(predictor.network, predictor.spec, out, dm_gain_model=gain, overwrite=cfg.overwrite,
                      info={"checkpoint": str(cfg.checkpoint)[-60:]})
    except ConfigError as err:
        raise CheckpointError(f"checkpoint {cfg.checkpoint!r} cannot be exported: {err}") from None
    summary = {"filter": str(out), "history": predictor.spec.to_dict(), "dm_gain_model": gain}
    if guard:
        summary["guard"] = {k: guard[k] for k in ("deployed", "gain_nm2", "scatter_nm2")}
    log(json.dumps(summary))
    return summary

