"""Training from telemetry alone: a predictor fitted on recorded ``y`` and ``wfs`` through an identified plant.

The simulator-truth path (:func:`eofnn.training.fit.fit_predictor`) learns ``-s(n)/g`` with the true ``s`` and
``g``; this one learns ``-s_hat(n)/g_hat`` with ``s_hat = wfs - DM_model(y)`` and ``DM_model``, ``g_hat`` from
:func:`eofnn.training.identify.identify_plant` (or a plant given by the user, or the nominal assumption ``DM(y) = y``,
which is what the study's open-loop EOF does and why it fails under a DM gain error).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from torch import nn

from eofnn.control.predictive import PredictiveController
from eofnn.data.history import HistorySpec
from eofnn.data.targets import TelemetryBatches, check_sequences, telemetry_grid
from eofnn.errors import ConfigError, TelemetryError
from eofnn.models.linear import LinearFilter
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.plant import Plant, PlantModel
from eofnn.sim.telemetry import Telemetry
from eofnn.training.identify import IdentifiedPlant
from eofnn.training.ridge import fit_closed_form, supports_closed_form


@dataclass
class TelemetryFit:
    """A predictor fitted from telemetry, the plant it was fitted through, and its training loss (nm², commands)."""

    network: nn.Module
    spec: HistorySpec
    dm_gain: float
    model_errors: dict
    plant_source: str
    train_loss: float
    info: dict = field(default_factory=dict)

    def controller(self) -> PredictiveController:
        """Loop-side controller; open loop reconstructs POL values with the DM gain the fit assumed."""
        return PredictiveController(self.network, self.spec, self.dm_gain if self.spec.kind == "open_loop" else 1.0)


def resolve_plant(plant: IdentifiedPlant | dict | None, delay_frames: int, grid: ActuatorGrid | None):
    """``(dm_response, dm_gain, model_errors, source)`` of an identified plant, model errors, or the nominal DM."""
    if isinstance(plant, IdentifiedPlant):
        return plant.dm_response("model"), float(plant.dm_gain or 0.0), plant.model_errors(), "identified"
    errors = dict(plant or {})
    model = Plant(delay_frames=delay_frames).with_errors(**errors)
    if model.misregistration_x or model.misregistration_y:
        if grid is None:
            raise TelemetryError("a misregistered DM model needs the actuator grid: put positions_m in the telemetry")
        return PlantModel(model, grid).apply_dm, model.dm_gain, errors, "given"
    return (lambda y: model.dm_gain * y), model.dm_gain, errors, "given" if errors else "nominal"


def fit_from_telemetry(telemetry: Telemetry | Sequence[Telemetry], spec: HistorySpec, network: nn.Module | None = None,
                       *, plant: IdentifiedPlant | dict | None = None, grid: ActuatorGrid | None = None,
                       alpha: float = 1e-9, alpha_relative: bool = True, batch_frames: int = 1024,
                       stop: int | None = None) -> TelemetryFit:
    """Fit a linear predictor in closed form (streamed ridge normal equations) on telemetry alone.

    Parameters
    ----------
    telemetry : Telemetry or sequence of Telemetry
        Recorded ``y`` and ``wfs`` (nm): one or several files, batched or not.
    spec : HistorySpec
        History kind, length and delay (the delay must be the telemetry's).
    network : nn.Module, optional
        A network with the closed-form interface (:class:`~eofnn.models.linear.LinearFilter`); by default a
        per-actuator linear filter (the study's EOF). Its previous weights are overwritten.
    plant : IdentifiedPlant, dict or None
        The DM model for POL values and targets: an identification result, a dict of model errors
        (``dm_gain``, ``misregistration_x``, ``misregistration_y``), or None for the nominal ``DM(y) = y``.
    grid : ActuatorGrid, optional
        Needed for a misregistered DM model given as a dict, when the telemetry holds no positions.
    alpha, alpha_relative : float, bool
        Ridge parameter (see :meth:`~eofnn.training.ridge.NormalEquations.solve`).
    batch_frames : int
        Frames per streamed batch.
    stop : int, optional
        Use frames before ``stop`` only (keep the rest for :func:`eofnn.analysis.replay.replay`).
    """
    sequences = check_sequences(telemetry, spec)
    n_act = sequences[0].y.shape[-1]
    first_item = telemetry if isinstance(telemetry, Telemetry) else telemetry[0]
    dm_response, dm_gain, errors, source = resolve_plant(plant, spec.delay_frames, telemetry_grid(first_item, grid))
    if network is None:
        network = LinearFilter(n_act, spec.n_taps)
    if not supports_closed_form(network):
        raise ConfigError(f"{type(network).__name__} has no closed-form interface (features, group_targets, "
                          "load_solution): train it with the Lightning task on TelemetryBatches")
    batches = TelemetryBatches(sequences, spec, dm_response, dm_gain, batch_frames, stop=stop)
    fitted = fit_closed_form(network, batches, alpha, alpha_relative)
    return TelemetryFit(network, spec, dm_gain, errors, source, fitted.train_loss,
                        {"condition": fitted.condition, "n_sequences": len(sequences)})
