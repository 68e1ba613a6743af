"""Every loop-side controller is built in one place, from its config, by a registry of builders keyed by name.

A builder takes the controller's config (anything with the fields it reads: ``gain``, ``leak``,
``dm_gain_model``) and, for a predictor, the trained network with its history spec. A new controller is one
decorated function; nothing else dispatches on the name.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from eofnn.control.baselines import Dithered, Integrator, PseudoIntegrator, Uncorrected
from eofnn.control.predictive import PredictiveController
from eofnn.errors import ConfigError
from eofnn.sim.loop import Controller

ControllerBuilder = Callable[[Any, Any], Controller]
_BUILDERS: dict[str, ControllerBuilder] = {}
#: Controllers that run a trained network (they need a predictor to be built).
NEEDS_PREDICTOR: set[str] = set()


def register_controller(name: str, needs_predictor: bool = False) -> Callable[[ControllerBuilder], ControllerBuilder]:
    """Decorator: ``builder(config, predictor)`` builds the controller called ``name``."""
    def decorate(builder: ControllerBuilder) -> ControllerBuilder:
        _BUILDERS[name] = builder
        if needs_predictor:
            NEEDS_PREDICTOR.add(name)
        return builder
    return decorate


def controller_names() -> tuple[str, ...]:
    """Names accepted as ``controller:`` in a config."""
    return tuple(_BUILDERS)


def build_controller(config: Any, predictor: Any = None) -> Controller:
    """The controller ``config.controller`` describes (``predictor``: the trained network it runs, if any)."""
    builder = _BUILDERS.get(config.controller)
    if builder is None:
        raise ConfigError(f"controller={config.controller!r} is invalid: it must be one of {', '.join(_BUILDERS)}")
    if config.controller in NEEDS_PREDICTOR and predictor is None:
        raise ConfigError(f"controller={config.controller!r} needs a trained predictor or a checkpoint")
    return builder(config, predictor)


@register_controller("uncorrected")
def _uncorrected(config: Any, predictor: Any) -> Controller:
    return Uncorrected()


@register_controller("pseudo_integrator")
def _pseudo_integrator(config: Any, predictor: Any) -> Controller:
    return PseudoIntegrator()


@register_controller("integrator")
def _integrator(config: Any, predictor: Any) -> Controller:
    return Integrator(config.gain, config.leak)


@register_controller("dithered_integrator")
def _dithered_integrator(config: Any, predictor: Any) -> Controller:
    """The integrator plus ``data.dither_nm`` of white dither: telemetry from which the plant can be identified."""
    return Dithered(Integrator(config.gain, config.leak), config.data.dither_nm, config.data.seed)


def dm_gain_model_of(config: Any, predictor: Any) -> float:
    """The DM gain a predictive controller believes: the config's if set, else the predictor's own model."""
    chosen = getattr(config, "dm_gain_model", None)
    if chosen is None:
        chosen = getattr(predictor, "dm_gain_model", 1.0) if predictor is not None else 1.0
    return float(chosen)


@register_controller("predictor", needs_predictor=True)
def _predictor(config: Any, predictor: Any) -> Controller:
    return PredictiveController(predictor.network, predictor.spec, dm_gain_model_of(config, predictor))
