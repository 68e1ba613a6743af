"""Simulation, in rooms: the actuator geometry (``grid.py``, ``layout.py``), the atmosphere (``atmosphere/``), what the
sensor sees of it (``sensing/``), the plant and the closed loop (``loop/``), and a scenario that assembles them
(``scenario.py``). Numpy and HCIPy stay here; telemetry, what a loop records, is the floor below
(:mod:`eofnn.telemetry`). The names below are imported when first read (:func:`eofnn.lazy.lazy_exports`), so that
importing one room (a config's, for the command line's parser) does not import the others."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eofnn.lazy import lazy_exports

if TYPE_CHECKING:
    from eofnn.sim.atmosphere.disturbances import Vibration
    from eofnn.sim.atmosphere.turbulence import Atmosphere, Layer, Turbulence
    from eofnn.sim.grid import ActuatorGrid
    from eofnn.sim.layout import ActuatorLayout
    from eofnn.sim.loop.plant import Plant
    from eofnn.sim.loop.runner import Controller, LoopInput, LoopResult, run_loop
    from eofnn.telemetry import Telemetry

__getattr__, __dir__ = lazy_exports(__name__, {
    "Vibration": "eofnn.sim.atmosphere.disturbances", "Atmosphere": "eofnn.sim.atmosphere.turbulence",
    "Layer": "eofnn.sim.atmosphere.turbulence", "Turbulence": "eofnn.sim.atmosphere.turbulence",
    "ActuatorGrid": "eofnn.sim.grid", "ActuatorLayout": "eofnn.sim.layout", "Plant": "eofnn.sim.loop.plant",
    "Controller": "eofnn.sim.loop.runner", "LoopInput": "eofnn.sim.loop.runner", "LoopResult": "eofnn.sim.loop.runner",
    "run_loop": "eofnn.sim.loop.runner", "Telemetry": "eofnn.telemetry",
})

__all__ = [
    "ActuatorGrid", "ActuatorLayout", "Atmosphere", "Controller", "Layer", "LoopInput", "LoopResult", "Plant", "Telemetry",
    "Turbulence", "Vibration", "run_loop",
]
