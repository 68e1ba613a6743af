"""Simulation, in rooms: the actuator geometry (``grid.py``, ``layout.py``), the atmosphere (``atmosphere/``), what the
sensor sees of it (``sensing/``), the plant and the closed loop (``loop/``), and a scenario that assembles them
(``scenario.py``). Numpy and HCIPy stay here; telemetry, what a loop records, is the floor below
(:mod:`eofnn.telemetry`)."""

from __future__ import annotations

from eofnn.sim.atmosphere.disturbances import Vibration
from eofnn.sim.atmosphere.turbulence import Atmosphere, Layer, Turbulence
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.layout import ActuatorLayout
from eofnn.sim.loop.plant import Plant
from eofnn.sim.loop.runner import Controller, LoopInput, LoopResult, run_loop
from eofnn.telemetry import Telemetry

__all__ = [
    "ActuatorGrid", "ActuatorLayout", "Atmosphere", "Controller", "Layer", "LoopInput", "LoopResult", "Plant", "Telemetry",
    "Turbulence", "Vibration", "run_loop",
]
