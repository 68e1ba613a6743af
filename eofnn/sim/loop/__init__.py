"""The plant and the loop: delay, DM (gain, misregistration, nonlinearity), WFS (gain, noise), and the closed-loop
runner that records :class:`~eofnn.telemetry.Telemetry`.

``eofnn.sim.loop`` was the runner's module before it became this room: its names still read from here for a
release, with a :class:`DeprecationWarning` naming :mod:`eofnn.sim.loop.runner`."""

from __future__ import annotations

#: The names the former module ``eofnn.sim.loop`` held, now in :mod:`eofnn.sim.loop.runner`.
_MOVED_TO_RUNNER = ("Controller", "LoopInput", "LoopResult", "record_loop", "run_loop")


def __getattr__(name: str):
    if name in _MOVED_TO_RUNNER:
        import importlib
        import warnings

        warnings.warn(f"eofnn.sim.loop.{name} moved to eofnn.sim.loop.runner.{name}: import it from there (the old "
                      "path goes in a later release)", DeprecationWarning, stacklevel=2)
        value = getattr(importlib.import_module("eofnn.sim.loop.runner"), name)
        globals()[name] = value  # warned once: ``from ... import`` reads the name twice
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
