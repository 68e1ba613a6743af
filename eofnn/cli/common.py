"""What the subcommands share: the light configuration groups (no torch: ``eofnn sweep --help`` stays fast; the
groups that hold a scenario are in :mod:`eofnn.cli.groups`), the YAML a command writes, progress lines.

Every subcommand is a function ``command(cfg, config_dump) -> result`` whose ``cfg`` is a dataclass below (or one
of its own that extends one); the command line builds each parser from the dataclass's fields and their numpydoc
(:mod:`eofnn.cli.commands`). A config is composed of the groups the floors below own: :class:`~eofnn.sim.scenario.
Scenario` (sim), :class:`~eofnn.evaluation.config.PredictorConfig` and :class:`~eofnn.evaluation.config.
EvaluationConfig` (evaluation, composing data, optimisation and adaptation groups of data, training and control).
"""

import sys
from dataclasses import asdict, dataclass
from typing import Any

import yaml


def log(message: str) -> None:
    """Progress lines go to stderr, so that stdout stays clean for what a command prints as its result."""
    print(message, file=sys.stderr, flush=True)


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def config_yaml(cfg: Any, dump: str | None = None) -> str:
    """The resolved YAML a command writes beside its outputs: ``dump``, the parser's own, from the command line; the
    config's fields when the command is called from Python."""
    return yaml.safe_dump(_plain(asdict(cfg)), sort_keys=False) if dump is None else dump


@dataclass(kw_only=True)
class Output:
    """Where a command writes.

    Parameters
    ----------
    out : str
        Output folder (must be empty unless --overwrite true).
    overwrite : bool
        Replace existing output.
    """

    out: str
    overwrite: bool = False


@dataclass(kw_only=True)
class TelemetryFiles:
    """Matrices that real-time computers keep beside their telemetry (docs/telemetry.md).

    Parameters
    ----------
    interaction_matrix : str, optional
        File (.npy, .npz, .fits) of the (S, K) interaction matrix, slopes = IM @ y, for telemetry recorded as slopes;
        replaces one in the telemetry file.
    reconstructor : str, optional
        File of the (K, S) reconstructor, wfs = R @ slopes (used as given).
    modal_basis : str, optional
        File of the (actuators, M) modal basis when y and wfs are modal coefficients.
    command_unit : str
        What one unit of y is, converted to nm on reading: 'surface' (nm of smooth DM surface, eofnn's), 'nm' (the
        same), 'peak' (nm at the peak of one actuator's influence function, OOPAO's: x 2.99 at coupling 0.35), 'um',
        'm', or a positive number of nm per unit (e.g. nm per volt).
    measurement_unit : str, optional
        What one unit of wfs (or of R @ slopes) is, as command_unit; default the same as command_unit.
    """

    interaction_matrix: str | None = None
    reconstructor: str | None = None
    modal_basis: str | None = None
    command_unit: str = "surface"
    measurement_unit: str | None = None


@dataclass(kw_only=True)
class TelemetryCommand(TelemetryFiles, Output):
    """A command that reads recorded telemetry (identify, replay).

    Parameters
    ----------
    telemetry : str or list of str
        Telemetry file, .fits or .npz, with y and wfs in nm, or a list [a.fits, b.fits] of files of one plant.
    """

    telemetry: str | list[str]
