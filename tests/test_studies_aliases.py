"""The studies moved from eofnn/interop to eofnn/studies (docs/design.md, "Floors"); their old import paths still work
for one release, warn DeprecationWarning once, and give the moved module's own objects."""

from __future__ import annotations

import importlib
import sys
import warnings

import pytest
from test_layering import ALIASES

MODULES = sorted(old for old in ALIASES if old != "eofnn.interop.pfc")


@pytest.mark.parametrize("old", MODULES)
def test_the_old_path_warns_and_is_the_moved_module(old, monkeypatch):
    new = importlib.import_module(ALIASES[old])
    monkeypatch.delitem(sys.modules, old, raising=False)
    with pytest.warns(DeprecationWarning, match=f"{old} moved to {ALIASES[old]}"):
        alias = importlib.import_module(old)
    assert alias is new
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once: a second import is the cached module, no warning
        assert importlib.import_module(old) is new


def test_a_public_name_of_a_moved_module_imports_from_the_old_path(monkeypatch):
    from eofnn.studies.antialias import AntiAliasConfig

    monkeypatch.delitem(sys.modules, "eofnn.interop.antialias", raising=False)
    with pytest.warns(DeprecationWarning):
        from eofnn.interop.antialias import AntiAliasConfig as old
    assert old is AntiAliasConfig


def test_pfc_in_loop_moved_and_the_lattice_adapter_stayed():
    from eofnn.interop import pfc
    from eofnn.studies.pfc import pfc_in_loop

    assert pfc.LatticeGrid.__module__ == "eofnn.interop.pfc"
    with pytest.warns(DeprecationWarning, match="eofnn.studies.pfc.pfc_in_loop"):
        assert pfc.pfc_in_loop is pfc_in_loop
    with pytest.raises(AttributeError, match="no_such_name"):
        pfc.no_such_name  # noqa: B018


def test_interop_holds_the_adapters_and_the_aliases_only():
    from pathlib import Path

    interop = Path(importlib.import_module("eofnn.interop").__file__).parent
    modules = {p.stem for p in interop.glob("*.py")} - {"__init__"}
    adapters = {"loop", "oopao", "oopao_pyramid", "hcipy", "shift", "pfc", "controls", "native", "map_reconstructor"}
    aliases = {old.rpartition(".")[2] for old in MODULES}
    assert modules == adapters | aliases
