"""Stability of an experiment's linear controllers: which analysis applies to which controller, in one place."""

from __future__ import annotations

from typing import Any

from eofnn.analysis.stability import LoopSetup, StabilityResult, analyse_filter, analyse_integrator
from eofnn.control.registry import dm_gain_model_of
from eofnn.models.linear import LinearFilter
from eofnn.sim.scenario import Scenario

#: Keys of :meth:`StabilityResult.to_dict` kept in a compare's summary (the per-actuator arrays are left out).
SUMMARY_KEYS = ("kind", "structure", "history_length", "stable", "max_root_modulus", "dm_gain_interval",
                "gain_margin_db", "worst_group", "worst_crossing_hz", "delay_margin_frames",
                "integer_delay_margin_frames", "analysis_seconds", "notes")


def controller_stability(config: Any, predictor: Any, scenario: Scenario) -> StabilityResult | None:
    """The analysis of a controller in ``scenario``: an integrator, or a predictor whose network is a
    :class:`~eofnn.models.linear.LinearFilter`; ``None`` for anything else (no linear model to analyse)."""
    setup = LoopSetup.from_plant(scenario.plant, scenario.frame_rate_hz, dm_gain_model_of(config, predictor))
    if config.controller == "integrator":
        return analyse_integrator(config.gain, config.leak, setup)
    if predictor is not None and isinstance(predictor.network, LinearFilter):
        return analyse_filter(predictor.network, predictor.spec, setup)
    return None


def summary(result: StabilityResult) -> dict:
    """The scalars of a stability result (stable, DM gain interval, delay margin, ...), for ``metrics`` files."""
    full = result.to_dict()
    return {key: full[key] for key in SUMMARY_KEYS if key in full}
