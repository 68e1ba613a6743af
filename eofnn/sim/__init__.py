"""Simulation: turbulence on the actuator grid, the AO plant and the closed-loop runner (numpy/HCIPy stay here)."""

from __future__ import annotations

from eofnn.sim.disturbances import Vibration
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.layout import ActuatorLayout
from eofnn.sim.loop import Controller, LoopInput, LoopResult, run_loop
from eofnn.sim.plant import Plant
from eofnn.sim.telemetry import Telemetry
from eofnn.sim.turbulence import Atmosphere, Layer, Turbulence

__all__ = [
    "ActuatorGrid", "ActuatorLayout", "Atmosphere", "Controller", "Layer", "LoopInput", "LoopResult", "Plant", "Telemetry",
    "Turbulence", "Vibration", "run_loop",
]
