"""Public import paths that moved keep working for a release: the old path warns DeprecationWarning naming the new one
and gives the very same objects (``eofnn.MOVED``; ``eofnn.sim.loop``'s former names)."""

from __future__ import annotations

import importlib
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import eofnn

ROOT = Path(__file__).resolve().parent.parent


def _fresh_import(name: str):
    sys.modules.pop(name, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(name)
    return module, [w for w in caught if issubclass(w.category, DeprecationWarning)]


@pytest.mark.parametrize("old, new", sorted(eofnn.MOVED.items()))
def test_a_moved_module_warns_and_reexports_the_same_objects(old, new):
    module, warned = _fresh_import(old)
    assert len(warned) == 1 and f"{old} moved to {new}" in str(warned[0].message)
    assert warned[0].filename == __file__  # the warning points at the import, not at the import machinery
    target = importlib.import_module(new)
    public = [n for n in vars(target) if not n.startswith("_")]
    assert public, new
    for name in public:
        assert getattr(module, name) is getattr(target, name)
    assert set(module.__all__) <= set(dir(module))


def test_the_moved_telemetry_module_reads_as_before():
    from eofnn.telemetry.record import Telemetry

    sys.modules.pop("eofnn.sim.telemetry", None)
    with pytest.warns(DeprecationWarning, match="eofnn.sim.telemetry moved to eofnn.telemetry.record"):
        from eofnn.sim.telemetry import Telemetry as old  # a user's script of before the move
    assert old is Telemetry
    namespace: dict = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        exec("from eofnn.sim.telemetry import *", namespace)
    assert namespace["Telemetry"] is Telemetry and "telemetry_path" in namespace


def test_no_old_path_shadows_a_real_module():
    for old in eofnn.MOVED:
        relative = Path(*old.split("."))
        assert not (ROOT / relative.with_suffix(".py")).exists() and not (ROOT / relative).is_dir(), old
    assert importlib.util.find_spec("eofnn.sim.nothing_here") is None


@pytest.mark.parametrize("name", ["run_loop", "record_loop", "LoopInput", "LoopResult", "Controller"])
def test_the_former_loop_module_names_read_from_the_loop_room(name):
    import eofnn.sim.loop as room
    from eofnn.sim.loop import runner

    room.__dict__.pop(name, None)
    with pytest.warns(DeprecationWarning, match=f"eofnn.sim.loop.{name} moved to eofnn.sim.loop.runner"):
        value = getattr(room, name)
    assert value is getattr(runner, name)
    with pytest.raises(AttributeError):
        room.not_a_name  # noqa: B018


@pytest.mark.cli
def test_a_script_of_before_the_move_runs_and_is_told_once():
    script = "from eofnn.sim.telemetry import Telemetry\nimport eofnn.sim.telemetry\nprint(Telemetry.__module__)\n"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "eofnn.telemetry.record"
    assert done.stderr.count("DeprecationWarning: eofnn.sim.telemetry moved to eofnn.telemetry.record") == 1
