"""``eofnn twin``: the twin of a user's system identified from its telemetry alone, as an eofnn scenario."""

from __future__ import annotations

import json
from dataclasses import dataclass

import yaml

import eofnn
from eofnn.cli.common import Output, log
from eofnn.outputs import check_output_folder, staged_folder
from eofnn.telemetry.units import OPTICAL_GAIN, check_units
from eofnn.validation import Interval, OrNone, check_value

# The identification imports torch, scipy and the simulator (seconds): imported in the function, so that the parser
# and its config errors answer without them.

DESCRIPTION = ("Identify a twin of the system that recorded the telemetry (FITS/npz with y, wfs or slopes, positions, "
               "the delay and the frame rate; docs/telemetry.md), from the telemetry alone: the pupil and valid "
               "subapertures, the DM gain x optical gain (from a dither), the WFS noise and its spatial colour, r0 "
               "and L0, and the frozen-flow layers (count, Cn2 fractions, winds), each with an uncertainty and its "
               "method. Writes DIR/twin.yaml (an eofnn scenario: eofnn fit --scenario DIR/twin.yaml) and "
               "DIR/identified.json.")


@dataclass(kw_only=True)
class TwinConfig(Output):
    """``eofnn twin``: a scenario identified from telemetry.

    Parameters
    ----------
    telemetry : str
        Telemetry file, .fits or .npz (docs/telemetry.md): y and wfs (nm), or slopes with an interaction matrix or a
        reconstructor; positions_m; the delay; the frame rate. s, eps and any simulator config are never read.
    interaction_matrix : str, optional
        File (.npy, .npz, .fits) of the (S, K) interaction matrix, slopes = IM @ y; replaces the file's. Its columns
        say which actuators the sensor sees (every actuator of the telemetry must move some slope), its rows which
        slopes respond (the valid subapertures).
    reconstructor : str, optional
        File of the (K, S) reconstructor, wfs = R @ slopes; replaces the file's (shape checked; the noise's spatial
        colour is compared with R R^T).
    mechanical_coupling : float, optional
        The DM's Gaussian influence functions' value one pitch away, for a record of slopes (default 0.35, with a
        warning).
    optical_gain : float or 'identified', optional
        The sensor's optical gain on sky (its response to the phase under seeing over its calibration's), where known
        (a model of the sensor, a gain-sensing camera): the dither identifies only the DM gain x the optical gain, so
        without it r0 and the noise are of the sensor's reading of the phase (a diffractive Shack-Hartmann's r0
        comes out optical_gain^(-6/5) high, with a warning); with it they are the phase's and the twin's DM gain is
        the product over it. 'identified': all of the identified product is the optical gain (the DM's gain is
        its interaction matrix's: the matrix measured on this DM, as on a real system; not OOPAO's study, whose DM
        gain is 2 on purpose).
    command_unit : str
        What one unit of y is: 'surface' (nm of smooth DM surface, eofnn's), 'nm' (the same), 'peak' (nm at the peak
        of one actuator's influence function, OOPAO's), 'um', 'm', or a positive number of nm per unit (e.g. nm per
        volt): the twin is in eofnn's units whichever.
    measurement_unit : str, optional
        What one unit of wfs (or of R @ slopes) is, as command_unit; default the same as command_unit.
    max_layers : int
        Most frozen-flow layers fitted.
    max_speed_mps : float
        Fastest wind searched (m/s).
    blocks : int
        Consecutive blocks the record is split into for the uncertainties and the layer count.
    screen_frames : int
        atmosphere.screen_frames of twin.yaml (the longest stream the twin will be asked for).
    seed : int
        Seed of the twin's reference streams (r0 and L0 are scaled from them).
    """

    telemetry: str
    interaction_matrix: str | None = None
    reconstructor: str | None = None
    mechanical_coupling: float | None = None
    optical_gain: float | str | None = None
    command_unit: str = "surface"
    measurement_unit: str | None = None
    max_layers: int = 3
    max_speed_mps: float = 40.0
    blocks: int = 4
    screen_frames: int = 10000
    seed: int = 0


def twin(cfg: TwinConfig, config_dump: str | None = None) -> dict:
    """Identify the twin of ``cfg.telemetry`` and write ``twin.yaml`` and ``identified.json`` into ``cfg.out``;
    returns the summary line."""
    check_value("mechanical_coupling", cfg.mechanical_coupling, OrNone(Interval(0, 1, closed="neither")))
    check_units(cfg.command_unit, cfg.measurement_unit)
    check_value("optical_gain", cfg.optical_gain, OPTICAL_GAIN)
    check_value("max_layers", cfg.max_layers, Interval(1, 3, integer=True))
    check_value("max_speed_mps", cfg.max_speed_mps, Interval(0, 200, closed="right", unit="m/s"))
    check_value("blocks", cfg.blocks, Interval(2, 100, integer=True))
    check_value("screen_frames", cfg.screen_frames, Interval(100, 10**7, integer=True, unit="frames"))
    out = check_output_folder(cfg.out, cfg.overwrite)
    result = identify(cfg)
    config = result.twin_config(cfg.screen_frames)
    with staged_folder(out, cfg.overwrite) as folder:
        (folder / "twin.yaml").write_text(
            f"# eofnn twin of {cfg.telemetry}, identified from its telemetry alone (identified.json: values, "
            "uncertainties, methods)\n" + yaml.safe_dump(config, sort_keys=False))
        result.to_json(folder / "identified.json")
    for warning in result.warnings:
        log(f"twin: {warning}")
    summary = {"twin": str(out / "twin.yaml"), "r0_m": result.value("r0_m"), "outer_scale_m": result.value("outer_scale_m"),
               "wfs_noise_nm": result.value("wfs_noise_nm"), "dm_gain": result.value("dm_gain"),
               "layers": [[round(lay["speed_mps"], 3), round(lay["direction_deg"], 2), round(lay["weight"], 3)]
                          for lay in result.layers]}
    log(json.dumps(summary))
    return summary


def identify(cfg: TwinConfig) -> eofnn.training.twin.TwinIdentification:
    """The identification of ``cfg.telemetry`` (its matrices replaced by the files given)."""
    from eofnn.telemetry.record import TELEMETRY_REQUIRED, Telemetry
    from eofnn.telemetry.spaces import read_matrix
    from eofnn.training.twin import identify_twin

    matrices = {name: read_matrix(path, name) for name, path in
                (("interaction_matrix", cfg.interaction_matrix), ("reconstructor", cfg.reconstructor)) if path}
    telemetry = Telemetry.load(cfg.telemetry, required=TELEMETRY_REQUIRED, space=matrices)
    if telemetry.measurement:
        log(f"telemetry {cfg.telemetry}: {telemetry.measurement}")
    return identify_twin(telemetry, interaction_matrix=matrices.get("interaction_matrix"),
                         reconstructor=matrices.get("reconstructor"), max_layers=cfg.max_layers,
                         max_speed_mps=cfg.max_speed_mps, blocks=cfg.blocks,
                         mechanical_coupling=cfg.mechanical_coupling, command_unit=cfg.command_unit,
                         measurement_unit=cfg.measurement_unit, optical_gain=cfg.optical_gain, seed=cfg.seed)
