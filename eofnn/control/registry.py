"""Every loop-side controller is built in one place, from its config, by a registry of builders keyed by name.

A builder takes the controller's config (anything with the fields it reads: ``gain``, ``leak``,
``dm_gain_model``) and, for a predictor, the trained network with its history spec. A new controller is one
decorated function; nothing else dispatches on the name.

The controllers' modules (torch) are imported by the builders when a controller is built, not here: the registry's
names and sets (``controller_names``, ``NEEDS_PREDICTOR``, ``FROM_TELEMETRY``), which config checks and ``--help``
read, come without them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from eofnn.errors import ConfigError

if TYPE_CHECKING:
    from eofnn.sim.loop.runner import Controller

ControllerBuilder = Callable[[Any, Any], "Controller"]
_BUILDERS: dict[str, ControllerBuilder] = {}
#: Controllers that run a trained network (they need a predictor to be built).
NEEDS_PREDICTOR: set[str] = set()
#: Controllers whose model is built from telemetry recorded in each scenario: name -> ``model(config, scenario)``.
#: The experiment passes that model to the builder in place of a predictor.
FROM_TELEMETRY: dict[str, Callable[[Any, Any], Any]] = {}


def register_controller(name: str, needs_predictor: bool = False,
                        from_telemetry: Callable[[Any, Any], Any] | None = None,
                        ) -> Callable[[ControllerBuilder], ControllerBuilder]:
    """Decorator: ``builder(config, predictor)`` builds the controller called ``name``; ``from_telemetry(config,
    scenario)``, if given, builds the model (passed as ``predictor``) from telemetry recorded in a scenario."""
    def decorate(builder: ControllerBuilder) -> ControllerBuilder:
        _BUILDERS[name] = builder
        if needs_predictor:
            NEEDS_PREDICTOR.add(name)
        if from_telemetry is not None:
            FROM_TELEMETRY[name] = from_telemetry
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
    if config.controller in FROM_TELEMETRY and predictor is None:
        raise ConfigError(f"controller={config.controller!r} needs its model built from telemetry (compare builds it "
                          "in each scenario)")
    return builder(config, predictor)


@register_controller("uncorrected")
def _uncorrected(config: Any, predictor: Any) -> Controller:
    from eofnn.control.baselines import Uncorrected

    return Uncorrected()


@register_controller("pseudo_integrator")
def _pseudo_integrator(config: Any, predictor: Any) -> Controller:
    from eofnn.control.baselines import PseudoIntegrator

    return PseudoIntegrator()


@register_controller("integrator")
def _integrator(config: Any, predictor: Any) -> Controller:
    from eofnn.control.baselines import Integrator

    return Integrator(config.gain, config.leak)


@register_controller("dithered_integrator")
def _dithered_integrator(config: Any, predictor: Any) -> Controller:
    """The integrator plus ``data.dither_nm`` of white dither: telemetry from which the plant can be identified."""
    from eofnn.control.baselines import Dithered, Integrator

    return Dithered(Integrator(config.gain, config.leak), config.data.dither_nm, config.data.seed)


def dm_gain_model_of(config: Any, predictor: Any) -> float:
    """The DM gain a predictive controller believes: the config's if set, else the predictor's own model
    (:func:`~eofnn.control.predictive.believed_dm_gain`)."""
    from eofnn.control.predictive import believed_dm_gain

    return believed_dm_gain(getattr(config, "dm_gain_model", None), predictor)


@register_controller("predictor", needs_predictor=True)
def _predictor(config: Any, predictor: Any) -> Controller:
    from eofnn.control.predictive import PredictiveController

    adaptation = getattr(config, "adaptation", None)
    if adaptation is not None and adaptation.method != "none":
        return adaptation.build(predictor, dm_gain_model_of(config, predictor))
    return PredictiveController(predictor.network, predictor.spec, dm_gain_model_of(config, predictor))


@register_controller("extrapolator")
def _extrapolator(config: Any, predictor: Any) -> Controller:
    """Polynomial extrapolation (``order``, least squares over ``smoothing`` more frames) of the POL signal over the
    plant's delay; nothing to train."""
    from eofnn.control.classical import Extrapolator

    return Extrapolator(config.order, dm_gain_model_of(config, None), getattr(config, "smoothing", 0))


def _modal_from_telemetry(builder_name: str) -> Callable[[Any, Any], Any]:
    """``model(config, scenario)``: record ``config.data`` telemetry in the scenario and build the modal model with
    :mod:`eofnn.control.modal`'s ``builder_name``, with the config's ``dm_gain_model`` or (unset) the DM gain the
    recording's dither measures."""
    def model(config: Any, scenario: Any) -> Any:
        from eofnn.control import modal

        build = getattr(modal, builder_name)
        return build(scenario, config.data, config.modes, getattr(config, "dm_gain_model", None))
    return model


@register_controller("modal_integrator", from_telemetry=_modal_from_telemetry("build_modal_integrator"))
def _modal_integrator(config: Any, predictor: Any) -> Controller:
    """One optimal integrator gain per KL mode (:func:`eofnn.control.modal.build_modal_integrator`)."""
    return replace(predictor)


def _lqg_from_telemetry(config: Any, scenario: Any) -> Any:
    """The LQG model of :func:`_modal_from_telemetry`, with the config's ``ar_order`` (2 unless set) and
    ``noise_scale`` (1 unless set)."""
    from eofnn.control.modal import build_lqg

    return build_lqg(scenario, config.data, config.modes, getattr(config, "dm_gain_model", None),
                     getattr(config, "ar_order", 2), getattr(config, "noise_scale", 1.0))


@register_controller("lqg", from_telemetry=_lqg_from_telemetry)
def _lqg(config: Any, predictor: Any) -> Controller:
    """Kalman filter + LQG command, AR(2) (or ``ar_order``) per KL mode (:func:`eofnn.control.modal.build_lqg`)."""
    return replace(predictor)


def _pfc_from_telemetry(config: Any, scenario: Any) -> Any:
    """The predictive Fourier model: ``config.data`` telemetry recorded in the scenario, winds identified from it
    (or ``config.pfc.winds``), with the config's ``dm_gain_model`` or (unset) the DM gain the dither measures."""
    from eofnn.control.frozen_flow import build_pfc

    return build_pfc(scenario, config.data, config.pfc, getattr(config, "dm_gain_model", None))


@register_controller("pfc", from_telemetry=_pfc_from_telemetry)
def _pfc(config: Any, predictor: Any) -> Controller:
    """Predictive Fourier control: a frozen-flow Kalman filter per spatial Fourier mode
    (:mod:`eofnn.control.fourier`, built by :func:`eofnn.control.frozen_flow.build_pfc`)."""
    return replace(predictor)
