"""Heavy libraries (torch, Lightning, HCIPy, scipy) imported on first use, not on import of the module that names them.

The command line builds a subcommand's parser from config dataclasses whose modules also hold the code that runs the
command; those modules name torch & co. as ``torch = lazy_module("torch")`` instead of ``import torch``, so that
``eofnn compare --help`` and a config error answer in a fraction of a second, before seconds of imports. The first
attribute read (``torch.zeros``) imports the library and puts the real module in place of the stand-in in the
namespace that named it, so code that runs pays nothing more than one import. A stand-in is never put in
``sys.modules``: ``"torch" in sys.modules`` still says whether torch was imported.

Only names read inside functions can be deferred: a class that subclasses ``nn.Module`` or a module-level constant
such as ``torch.float64`` imports the library when its module is imported (that is why the config groups live in
modules free of such definitions).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from types import ModuleType
from typing import Any

#: Special names whose reading is a use of the module (the others are introspection, answered without importing it).
_DUNDERS_THAT_IMPORT = frozenset({"__version__", "__file__", "__path__", "__all__", "__spec__", "__loader__"})


class LazyModule:
    """A stand-in for the module ``name``, imported when an attribute of it is first read.

    ``namespace`` is the globals of the module that holds the stand-in: once imported, every name there bound to the
    stand-in is rebound to the real module.
    """

    __slots__ = ("_name", "_namespace", "_module")

    def __init__(self, name: str, namespace: dict[str, Any]) -> None:
        object.__setattr__(self, "_name", name)
        object.__setattr__(self, "_namespace", namespace)
        object.__setattr__(self, "_module", None)

    def load(self) -> ModuleType:
        """Import the module (once) and rebind the names in the holder's namespace that refer to this stand-in."""
        module = object.__getattribute__(self, "_module")
        if module is None:
            module = importlib.import_module(object.__getattribute__(self, "_name"))
            object.__setattr__(self, "_module", module)
            namespace = object.__getattribute__(self, "_namespace")
            for key, value in list(namespace.items()):
                if value is self:
                    namespace[key] = module
        return module

    def __getattr__(self, attr: str) -> Any:
        if (attr.startswith("__") and attr.endswith("__") and attr not in _DUNDERS_THAT_IMPORT
                and object.__getattribute__(self, "_module") is None):
            # Introspection (``hasattr(value, "__args__")``, as jsonargparse does on a config module's globals) is
            # not a use: it must not import the library.
            raise AttributeError(attr)
        return getattr(self.load(), attr)

    def __setattr__(self, attr: str, value: Any) -> None:
        setattr(self.load(), attr, value)

    def __dir__(self) -> list[str]:
        return dir(self.load())

    def __repr__(self) -> str:
        name = object.__getattribute__(self, "_name")
        state = "imported" if object.__getattribute__(self, "_module") is not None else "not imported yet"
        return f"<lazy module {name!r} ({state})>"


def lazy_module(name: str) -> Any:
    """``name`` (e.g. ``"torch"``, ``"torch.nn"``), imported when first used; the module itself when it already is.

    Call it at the top level of a module, as ``torch = lazy_module("torch")``: the stand-in rebinds itself in the
    caller's globals on first use.
    """
    if name in sys.modules:
        return sys.modules[name]
    return LazyModule(name, sys._getframe(1).f_globals)


def lazy_exports(package: str, homes: dict[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """A package's ``__getattr__`` and ``__dir__`` (PEP 562) that import each name it re-exports from its home module
    when first read: ``homes`` maps a name to the module that defines it. Importing ``eofnn.sim.grid`` then runs
    ``eofnn/sim/__init__.py`` without importing every room of the simulator."""

    def __getattr__(name: str) -> Any:
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(home), name)
        setattr(sys.modules[package], name, value)  # read once: later reads are plain attributes
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(homes))

    return __getattr__, __dir__


__all__ = ["LazyModule", "lazy_exports", "lazy_module"]
