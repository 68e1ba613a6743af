"""Loading a predictor checkpoint safely: ``weights_only`` tensors, and networks only from an allowlist.

A checkpoint names the class of its network. Importing a module runs its code, so a checkpoint from someone
else is only rebuilt when that class is eofnn's own or one the user trusts by name; the check is made on the
string read from the file, before anything is imported.
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path

import torch

from eofnn.errors import CheckpointError, ConfigError
from eofnn.models.build import check_trusted
from eofnn.sim.scenario import Scenario
from eofnn.training.fit import TrainedPredictor
from eofnn.training.task import PredictorTask

#: Errors that mean "this file is not a checkpoint eofnn wrote" (torch raises any of them on foreign files).
_UNREADABLE = (KeyError, TypeError, RuntimeError, ValueError, EOFError, AttributeError, OSError)


def _hyperparameters(path: Path) -> dict:
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
        hp = ckpt["hyper_parameters"]
        class_path = hp["network"]["class_path"]
        if not isinstance(class_path, str) or not isinstance(ckpt["state_dict"], dict):
            raise TypeError("malformed")
    except Exception as err:  # UnpicklingError, EOFError, KeyError... for files that are not eofnn checkpoints
        raise CheckpointError(f"checkpoint {str(path)!r} is not an eofnn predictor checkpoint "
                              f"({type(err).__name__})") from None
    return hp


def load_predictor(path: str | Path, scenario: Scenario | None = None, history_length: int | None = None,
                   trusted_networks: Collection[str] = ()) -> TrainedPredictor:
    """Rebuild a predictor from a checkpoint written by :func:`~eofnn.training.fit.fit_predictor`.

    Parameters
    ----------
    path : path
        The ``.ckpt`` file.
    scenario : Scenario, optional
        Check that the predictor fits it (actuators, delay), with a one-line error if not.
    history_length : int, optional
        Check the history length too.
    trusted_networks : collection of str
        Class paths beyond eofnn's own networks that this checkpoint may name (the user's own modules).
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist")
    hp = _hyperparameters(path)
    check_trusted(hp["network"]["class_path"], trusted_networks, f"checkpoint {str(path)!r}")
    try:
        task = PredictorTask.load_from_checkpoint(path, map_location="cpu", weights_only=True)
    except ConfigError:
        raise
    except _UNREADABLE as err:
        raise CheckpointError(f"checkpoint {str(path)!r} is not an eofnn predictor checkpoint "
                              f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})") from None
    for name, value in task.network.state_dict().items():
        if value.is_floating_point() and not torch.isfinite(value).all():
            raise CheckpointError(f"checkpoint {str(path)!r} holds non-finite weights in {name!r}")
    network = task.network.eval()
    predictor = TrainedPredictor(network, task.spec, dict(hp["network"]), int(hp["n_actuators"]), dict(hp["info"] or {}))
    if scenario is not None:
        predictor.check_fits(scenario, f"checkpoint {str(path)!r}", history_length)
    return predictor
