"""eofnn: predictive wavefront control for adaptive optics, in simulated closed loop.

Modules that moved keep their old import path for a release: importing one (``eofnn.sim.telemetry``) warns
:class:`DeprecationWarning`, naming the new path, and gives a module that reads every name from the new one
(:data:`MOVED`). The old paths are found by a finder placed after Python's own, so they never shadow a real module.
"""

from __future__ import annotations

import sys
import types
import warnings
from importlib.machinery import ModuleSpec

__version__ = "0.1.0"

#: Old import path -> new import path of every public module that moved.
MOVED = {
    "eofnn.sim.telemetry": "eofnn.telemetry.record",
    "eofnn.sim.telemetry_file": "eofnn.telemetry.file",
    "eofnn.sim.telemetry_readers": "eofnn.telemetry.readers",
    "eofnn.sim.spaces": "eofnn.telemetry.spaces",
    "eofnn.sim.delay": "eofnn.delay",
    "eofnn.sim.anywind": "eofnn.sim.atmosphere.anywind",
    "eofnn.sim.changes": "eofnn.sim.atmosphere.changes",
    "eofnn.sim.disturbances": "eofnn.sim.atmosphere.disturbances",
    "eofnn.sim.exact": "eofnn.sim.atmosphere.exact",
    "eofnn.sim.hcipy_pupil": "eofnn.sim.atmosphere.hcipy_pupil",
    "eofnn.sim.strip": "eofnn.sim.atmosphere.strip",
    "eofnn.sim.turbulence": "eofnn.sim.atmosphere.turbulence",
    "eofnn.sim.plant": "eofnn.sim.loop.plant",
    "eofnn.main": "eofnn.cli.commands",
    "eofnn.console": "eofnn.cli.console",
    "eofnn.analysis.replay": "eofnn.evaluation.replay",
    "eofnn.analysis.figures": "eofnn.reporting.stability",
    "eofnn.evaluation.report": "eofnn.reporting.report",
    "eofnn.cli.sweep.figures": "eofnn.reporting.sweep",
    "eofnn.models.controllers": "eofnn.control.baselines",
    "eofnn.models.predictive": "eofnn.control.predictive",
}


def _caller_stacklevel() -> int:
    """The ``stacklevel`` that points a warning raised inside the import machinery at the importing code
    (:func:`warnings.warn` does not count the frames of ``importlib._bootstrap``)."""
    frame, level = sys._getframe(1), 1
    while frame is not None:
        name = frame.f_code.co_filename
        internal = "importlib" in name and "_bootstrap" in name  # skipped by warnings.warn
        if "importlib" not in name and name != __file__:  # importlib.import_module included
            return level
        frame, level = frame.f_back, level + (not internal)
    return level


class _MovedModule(types.ModuleType):
    """The old path of a moved module: every name is read from the new module (the same objects)."""

    def __init__(self, name: str, target: types.ModuleType) -> None:
        super().__init__(name, f"Deprecated: moved to :mod:`{target.__name__}`.")
        self._target = target
        self.__all__ = list(getattr(target, "__all__", [n for n in vars(target) if not n.startswith("_")]))

    def __getattr__(self, name: str):
        return getattr(self._target, name)

    def __dir__(self) -> list[str]:
        return sorted(set(dir(self._target)))


class _MovedLoader:
    def __init__(self, new: str) -> None:
        self.new = new

    def create_module(self, spec: ModuleSpec) -> types.ModuleType:
        warnings.warn(f"{spec.name} moved to {self.new}: import it from there (the old path goes in a later "
                      "release)", DeprecationWarning, stacklevel=_caller_stacklevel())
        import importlib

        return _MovedModule(spec.name, importlib.import_module(self.new))

    def exec_module(self, module: types.ModuleType) -> None:
        pass


class _MovedFinder:
    """Finds the old path of a module in :data:`MOVED`; placed last on ``sys.meta_path``."""

    @staticmethod
    def find_spec(name: str, path=None, target=None) -> ModuleSpec | None:
        new = MOVED.get(name)
        return None if new is None else ModuleSpec(name, _MovedLoader(new))


if not any(isinstance(finder, _MovedFinder) for finder in sys.meta_path):
    sys.meta_path.append(_MovedFinder())
