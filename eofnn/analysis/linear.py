"""Stability of an experiment's linear controllers: which analysis applies to which controller (and to what its
fallback deploys), in one place."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import torch

from eofnn.analysis.block import CoupledAnalysisUnavailable
from eofnn.analysis.response import analyse_response
from eofnn.analysis.stability import (
    LoopSetup,
    StabilityResult,
    analyse,
    analyse_filter,
    analyse_integrator,
    analyse_polynomials,
    controller_polynomials,
    default_frequencies_hz,
    integrator_weights,
)
from eofnn.control.classical import ModalLQG, extrapolator_filter
from eofnn.control.fourier import FourierPredictor
from eofnn.control.registry import FROM_TELEMETRY, dm_gain_model_of
from eofnn.models.linear import LinearFilter
from eofnn.sim.scenario import Scenario

#: Keys of :meth:`StabilityResult.to_dict` kept in a compare's summary (the per-actuator arrays are left out).
SUMMARY_KEYS = ("kind", "structure", "history_length", "stable", "max_root_modulus", "dm_gain_interval",
                "gain_margin_db", "worst_group", "worst_crossing_hz", "delay_margin_frames",
                "integer_delay_margin_frames", "analysis_seconds", "notes")


def controller_stability(config: Any, predictor: Any, scenario: Scenario, fallback: Any = None
                         ) -> StabilityResult | None:
    """The analysis of a controller in ``scenario``: an integrator, a classical baseline (the extrapolator as its
    open-loop filter; the modal integrator and LQG, whose model is passed as ``predictor``, per mode), or a
    predictor whose network is a :class:`~eofnn.models.linear.LinearFilter`; ``None`` for anything else (no
    linear model to analyse). With ``fallback`` (the controller's fallback decision), what it deploys
    (:func:`fallback_stability`)."""
    if fallback is not None:
        return fallback_stability(fallback, config, predictor, scenario)
    setup = LoopSetup.from_plant(scenario.plant, scenario.frame_rate_hz, dm_gain_model_of(config, predictor))
    if config.controller == "integrator":
        return analyse_integrator(config.gain, config.leak, setup)
    if config.controller == "extrapolator":
        network, spec = extrapolator_filter(config.order, scenario.plant.delay_frames, setup.dm_gain_model,
                                            getattr(config, "smoothing", 0))
        return analyse_filter(network, spec, setup)
    if config.controller in FROM_TELEMETRY and hasattr(predictor, "polynomials"):
        return modal_stability(predictor, setup)
    adaptation = getattr(config, "adaptation", None)
    if adaptation is not None and adaptation.method != "none":
        return None  # a filter that changes every frame has no fixed characteristic polynomial
    if predictor is not None and isinstance(predictor.network, LinearFilter):
        return analyse_filter(predictor.network, predictor.spec, setup)
    return None


def modal_stability(model: Any, setup: LoopSetup) -> StabilityResult:
    """A modal controller (``model.polynomials()``: per-mode ``D(z), N(z)``) analysed with the modes as groups.

    The modes decouple the loop when the DM acts as ``g`` times the command on every mode (no misregistration),
    as the per-actuator analysis of a filter assumes for actuators. Predictive Fourier control's spatial Fourier
    modes (complex, one of each conjugate pair) decouple it only approximately on a pupil (its module says why;
    ``tests/test_pfc.py`` measures the DM-gain limit against simulation); they are analysed from their frequency
    responses and state spaces (:mod:`eofnn.analysis.response`: their polynomials' roots are too ill-conditioned).
    """
    start = time.perf_counter()
    frequencies = default_frequencies_hz(setup.frame_rate_hz)
    if isinstance(model, FourierPredictor):
        result = analyse_response(model.frequency_response, lambda plant: model.closed_loop_moduli(
            plant.dm_gain, plant.wfs_gain, plant.delay_frames), model.transition.shape[0], setup, frequencies,
            kind="open_loop", structure="modal", history_length=int(model.transition.shape[1]))
        result.notes.append("groups are the controller's modes (spatial Fourier modes, taken as decoupled)")
    else:
        d_poly, n_poly = model.polynomials()
        kind, length = ("open_loop", 2) if isinstance(model, ModalLQG) else ("closed_loop", 1)
        result = analyse_polynomials(d_poly, n_poly, setup, frequencies, kind=kind, structure="modal",
                                     history_length=length)
        result.notes.append("groups are the controller's modes")
    result.analysis_seconds = time.perf_counter() - start
    return result


def fallback_stability(decision: Any, config: Any, predictor: Any, scenario: Scenario) -> StabilityResult | None:
    """The analytic stability of what ``decision`` deploys: the integrator's, the predictor's own (``None`` when it
    has no linear model), or the composite's with its modes as groups, the predictor's filter on those it keeps and
    the integrator's on the others. That split holds where the filter acts alike on every mode (a shared filter, on
    any modes) or the modes are its own groups (a per-actuator filter, ``modes: actuators``); anything else is
    coupled, and raises :class:`~eofnn.analysis.block.CoupledAnalysisUnavailable` (reported like a network's: no
    analytic margins). ``decision`` is a :class:`~eofnn.evaluation.fallback.FallbackDecision`."""
    if decision.deployed == "predictor":
        return controller_stability(config, predictor, scenario)
    setup = LoopSetup.from_plant(scenario.plant, scenario.frame_rate_hz, dm_gain_model_of(config, predictor))
    if decision.deployed == "integrator":
        return analyse_integrator(decision.gain, 0.0, setup)
    network, kept = getattr(predictor, "network", None), decision.kept
    structure = getattr(network, "structure", None)
    if not isinstance(network, LinearFilter) or structure not in ("shared", "per_actuator") or (
            structure == "per_actuator" and kept.dim() == 2):
        raise CoupledAnalysisUnavailable(
            f"the per-mode fallback of a {structure or type(network).__name__} "
            f"{'filter' if isinstance(network, LinearFilter) else 'network'} on {decision.report['modes']} modes "
            "couples the modes (no linear model by groups; a shared filter, or modes: actuators with a per-actuator "
            "filter, has one)")
    spec = predictor.spec
    if setup.controller_delay_frames is None:
        setup = replace(setup, controller_delay_frames=spec.delay_frames)
    d_p, n_p = controller_polynomials(network.weight.detach(), spec.kind, spec.history_length, setup.dm_gain_model,
                                      setup.controller_delay)
    d_i, n_i = controller_polynomials(integrator_weights(decision.gain), "closed_loop", 1)
    if kept.dim() == 1:
        mask = kept
    else:  # a shared filter acts alike on every mode: M groups of its own, K - M of the integrator
        mask = torch.arange(kept.shape[0]) < kept.shape[1]
    k = mask.shape[0]

    def stack(own: torch.Tensor, integrator: torch.Tensor) -> torch.Tensor:
        length = max(own.shape[1], integrator.shape[1])
        own = torch.nn.functional.pad(own, (0, length - own.shape[1])).expand(k, -1)
        integrator = torch.nn.functional.pad(integrator, (0, length - integrator.shape[1])).expand(k, -1)
        return torch.where(mask[:, None], own, integrator)

    result = analyse_polynomials(stack(d_p, d_i), stack(n_p, n_i), setup, default_frequencies_hz(setup.frame_rate_hz),
                                 kind=spec.kind, structure=structure, history_length=spec.history_length)
    result.notes.append(f"groups are the fallback's modes: the predictor's filter on {int(mask.sum())}, the "
                        f"integrator (gain {decision.gain:g}) on {k - int(mask.sum())}")
    return result


def summary(result: StabilityResult, scenario: Scenario | None = None) -> dict:
    """The scalars of a stability result (stable, DM gain interval, delay margin, ...), for ``metrics`` files; in a
    pyramid ``scenario`` also the stable optical-gain interval (``"optical_gain"``, :func:`optical_gain_interval`)."""
    full = result.to_dict()
    out = {key: full[key] for key in SUMMARY_KEYS if key in full}
    if scenario is not None and scenario.sensor.is_pyramid:  # its optical gain multiplies the plant as a DM gain
        compensation = None if not scenario.sensor.optical_gain_compensation else (  # calibrated on its own stream
            scenario.turbulence(0, "test").compensation(scenario.plant))
        interval = optical_gain_interval(out, float(scenario.plant.dm_gain),
                                         None if compensation is None else compensation.divided_by())
        if interval is not None:
            out["optical_gain"] = interval
    return out


def dm_gain_margin(frame_rate_hz: float = 1000.0):
    """``margin(network, weights, spec, plant_dm_gain, dm_gain_model)``: the stable DM-gain interval, relative to
    ``plant_dm_gain`` (the DM gain of the plant the filter is made for), of a linear filter shaped like ``network``
    with other ``weights``, reading ``spec`` histories; ``None`` when that loop is unstable. What
    ``optimization.select`` checks each alpha of the path with (no delay margin, no transfer functions)."""
    def margin(network, weights: torch.Tensor, spec, plant_dm_gain: float, dm_gain_model: float):
        setup = LoopSetup(spec.delay_frames, plant_dm_gain, 1.0, dm_gain_model, spec.delay_frames, frame_rate_hz)
        result = analyse(weights, spec.kind, spec.history_length, setup, structure=network.structure,
                         neighbours=getattr(network, "neighbours", None),
                         frequencies_hz=torch.empty(0, dtype=torch.float64), delay_margin=False)
        if not result.stable:
            return None
        low, high = result.gain_margin
        return low / plant_dm_gain, high / plant_dm_gain
    return margin


def optical_gain_interval(summary: dict, dm_gain: float, compensation_gains=None) -> dict | None:
    """A pyramid's stable optical-gain interval from a stability ``summary``'s DM-gain interval (``None`` when the
    loop is unstable).

    The analysis models the sensor as linear about a flat wavefront (the reconstructor's calibration): about the
    loop's residual the pyramid's response to mode ``m`` is ``og_m`` times that, and a compensation
    (``compensation_gains``: the ``c_m`` it divides each mode's reconstruction by) divides it by ``c_m``. The loop
    gain of mode ``m`` is then ``g og_m / c_m`` (``c_m = 1`` uncompensated) for a DM gain ``g``: the optical gain
    multiplies the plant as the DM gain does. At the scenario's DM gain ``g0`` (``dm_gain``) and a stable DM-gain
    interval ``[g_lo, g_hi]``, mode ``m`` is stable for ``og_m / c_m`` in ``[g_lo / g0, g_hi / g0]``
    (``"relative_interval"``; every mode is assumed to share the analysed groups' interval). ``"interval"`` is that
    times the assumed gain (``"assumed"``: 1 uncompensated; the compensation's mean gain, ``"compensation_range"``
    the least and greatest ``c_m``), ``None`` for an unbounded end."""
    if not summary.get("stable") or summary.get("dm_gain_interval") is None or dm_gain <= 0:
        return None
    low, high = summary["dm_gain_interval"]
    relative = [max(low or 0.0, 0.0) / dm_gain, None if high is None else high / dm_gain]
    out = {"relative_interval": relative, "assumed": 1.0,
           "assumed_is": "the pyramid's response about a flat wavefront (uncompensated): 1"}
    if compensation_gains is not None:
        gains = [float(c) for c in compensation_gains]
        out["assumed"] = sum(gains) / len(gains)
        out["compensation_range"] = [min(gains), max(gains)]
        out["assumed_is"] = ("the mean of the gains the compensation divides each mode by (mode m: its own gain c_m "
                             "times relative_interval)")
    out["interval"] = [relative[0] * out["assumed"], None if high is None else relative[1] * out["assumed"]]
    return out
