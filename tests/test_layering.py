"""Lower floors never import higher ones (../shared/DESIGN.md, data flow): a walk over every import in eofnn/."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

#: Floors from the bottom up; a module may import its own floor and those below it.
FLOORS = ["sim", "data", "models", "control", "training", "evaluation", "interop", "cli"]
#: Packages that sit on a floor of another name.
SAME_FLOOR = {"analysis": "evaluation", "main": "cli", "console": "cli"}
#: Leaf modules anyone may import; they import nothing of eofnn above themselves.
BASE = {"errors", "validation", "seeding", "outputs", "resources"}
#: Modules that must stand alone (copied into a real-time computer): no eofnn import at all.
STANDALONE = {"runtime"}


def _floor(package: str) -> int | None:
    name = SAME_FLOOR.get(package, package)
    return FLOORS.index(name) if name in FLOORS else None


def _imports(path: Path, module: str) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the importing module
                base = module.split(".")[: -node.level]
                found.append((node.lineno, ".".join(base + ([node.module] if node.module else []))))
            elif node.module:
                found.append((node.lineno, node.module))
    return [(line, name) for line, name in found if name == "eofnn" or name.startswith("eofnn.")]


def forbidden_imports(root: Path) -> list[str]:
    """``file:line a -> b`` for every import in the package at ``root`` that reaches up a floor."""
    problems = []
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        module = ".".join(parts)
        top = parts[1] if len(parts) > 1 else ""
        for line, name in _imports(path, module):
            target = name.split(".")[1] if "." in name else ""
            where = f"{path.relative_to(root.parent)}:{line} {module} -> {name}"
            if top in STANDALONE:
                problems.append(where)
            elif top in BASE:
                if target not in BASE:
                    problems.append(where)
            elif target in STANDALONE or target in BASE or target in ("", "__init__"):
                continue
            else:
                mine, theirs = _floor(top), _floor(target)
                if theirs is None:
                    problems.append(where + " (unknown floor)")
                elif mine is not None and theirs > mine:
                    problems.append(where)
    return problems


def test_no_floor_imports_a_higher_one():
    root = Path(__file__).parent.parent / "eofnn"
    assert forbidden_imports(root) == []


def test_every_package_has_a_floor():
    root = Path(__file__).parent.parent / "eofnn"
    tops = {p.name if p.is_dir() else p.stem for p in root.iterdir() if p.suffix == ".py" or (p / "__init__.py").exists()}
    unknown = tops - BASE - STANDALONE - {"__init__"} - set(FLOORS) - set(SAME_FLOOR)
    assert not unknown, f"give these a floor in tests/test_layering.py: {sorted(unknown)}"


@pytest.mark.parametrize("source, target, bad", [
    ("sim/turbulence.py", "from eofnn.training.fit import fit_predictor", True),
    ("data/stream.py", "import eofnn.models.linear", True),
    ("models/mlp.py", "from eofnn.control import Integrator", True),
    ("errors.py", "from eofnn.sim import grid", True),
    ("training/fit.py", "from eofnn.control.baselines import Integrator", False),
    ("evaluation/report.py", "from eofnn.errors import ConfigError", False),
])
def test_the_check_catches_a_forbidden_import(tmp_path, source, target, bad):
    """The checker itself: a tiny tree with one import added fails exactly when the import reaches up."""
    root = tmp_path / "eofnn"
    path = root / source
    path.parent.mkdir(parents=True)
    path.write_text(f"{target}\n")
    assert bool(forbidden_imports(root)) is bad
