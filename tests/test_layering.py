"""Lower floors never import higher ones (docs/design.md, "Floors"): a walk over every import in eofnn/."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

#: Floors from the bottom up; a module may import its own floor and those below it.
FLOORS = ["telemetry", "sim", "data", "models", "control", "analysis", "training", "evaluation", "interop", "reporting", "cli",
          "studies"]
#: Leaf modules anyone may import; they import nothing of eofnn above themselves.
BASE = {"errors", "validation", "seeding", "outputs", "claims", "resources", "delay", "lazy"}
#: Modules that must stand alone (copied into a real-time computer): no eofnn import at all.
STANDALONE = {"runtime"}
#: Deprecated aliases (docs/design.md, "Floors"): a module left at the old path of one that moved up to ``studies``
#: may import the module it stands for, for one release; no other import of theirs climbs.
ALIASES = {f"eofnn.interop.{name}": f"eofnn.studies.{name}"
           for name in ("antialias", "transfer", "study", "sh_compare", "sh_diagnostics", "sh_system", "report", "pfc")}


def _floor(package: str) -> int | None:
    return FLOORS.index(package) if package in FLOORS else None


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
            if ALIASES.get(module) == name:
                continue
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
    unknown = tops - BASE - STANDALONE - {"__init__"} - set(FLOORS)
    assert not unknown, f"give these a floor in tests/test_layering.py: {sorted(unknown)}"


@pytest.mark.parametrize("source, target, bad", [
    ("sim/turbulence.py", "from eofnn.training.fit import fit_predictor", True),
    ("data/stream.py", "import eofnn.models.linear", True),
    ("models/mlp.py", "from eofnn.control import Integrator", True),
    ("errors.py", "from eofnn.sim import grid", True),
    ("training/fit.py", "from eofnn.control.baselines import Integrator", False),
    ("reporting/report.py", "from eofnn.errors import ConfigError", False),
    ("analysis/linear.py", "from eofnn.evaluation.metrics import WelchPSD", True),
    ("evaluation/replay.py", "from eofnn.reporting.replay import replay_figure", True),
])
def test_the_check_catches_a_forbidden_import(tmp_path, source, target, bad):
    """The checker itself: a tiny tree with one import added fails exactly when the import reaches up."""
    root = tmp_path / "eofnn"
    path = root / source
    path.parent.mkdir(parents=True)
    path.write_text(f"{target}\n")
    assert bool(forbidden_imports(root)) is bad


@pytest.mark.parametrize("target, bad", [
    ("import eofnn.studies.antialias as _moved", False),  # the module it stands for
    ("from eofnn.studies.transfer import eofnn_twin", True),  # another study
    ("from eofnn.cli.main import main", True),
])
def test_an_alias_may_import_only_the_module_it_stands_for(tmp_path, target, bad):
    root = tmp_path / "eofnn"
    for source, text in (("interop/antialias.py", target), ("studies/antialias.py", ""), ("studies/transfer.py", ""),
                         ("cli/main.py", "")):
        (root / source).parent.mkdir(parents=True, exist_ok=True)
        (root / source).write_text(text + "\n")
    assert bool(forbidden_imports(root)) is bad


def folder_graph(root: Path) -> dict[str, set[str]]:
    """Folder (or top-level module) -> the folders its modules import, leaf modules included."""
    graph: dict[str, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        top = parts[1] if len(parts) > 1 else ""
        for _, name in _imports(path, ".".join(parts)):
            if ALIASES.get(".".join(parts)) == name:
                continue
            target = name.split(".")[1] if "." in name else ""
            if target and target != top and target != "__init__":
                graph.setdefault(top, set()).add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every circle of imports between folders, each as ``[a, b, ..., a]`` (depth-first search)."""
    found, state = [], {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                found.append(trail[trail.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = "done"

    for start in sorted(graph):
        if start not in state:
            visit(start, [start])
    return found


def test_no_circle_of_imports_between_folders():
    assert cycles(folder_graph(Path(__file__).parent.parent / "eofnn")) == []


def test_the_circle_check_finds_a_circle(tmp_path):
    root = tmp_path / "eofnn"
    for source, target in (("training/a.py", "from eofnn.evaluation import b"),
                           ("evaluation/b.py", "from eofnn.analysis import c"),
                           ("analysis/c.py", "import eofnn.training.a"), ("sim/d.py", "")):
        (root / source).parent.mkdir(parents=True, exist_ok=True)
        (root / source).write_text(target + "\n")
    assert cycles(folder_graph(root)) == [["analysis", "training", "evaluation", "analysis"]]


def test_figures_live_in_one_room():
    """Only eofnn/reporting/ imports matplotlib, and no library module chooses a backend (the command line does, at
    its entry: eofnn.cli.main.choose_backend)."""
    root = Path(__file__).parent.parent / "eofnn"
    outside = [str(path.relative_to(root)) for path in sorted(root.rglob("*.py"))
               if path.relative_to(root).parts[0] != "reporting"
               and any(name == "matplotlib" or name.startswith("matplotlib.")
                       for node in ast.walk(ast.parse(path.read_text()))
                       for name in ([a.name for a in node.names] if isinstance(node, ast.Import) else
                                    [node.module or ""] if isinstance(node, ast.ImportFrom) else []))]
    assert outside == []
    choosers = [str(path.relative_to(root)) for path in sorted(root.rglob("*.py")) if ".use(" in path.read_text()
                and "matplotlib" in path.read_text()]
    assert choosers == ["cli/main.py"]


def module_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the eofnn modules it imports (files; a package is its ``__init__``), imports inside functions and
    ``TYPE_CHECKING`` blocks included: a circle of files within a floor is a circle even when it is deferred."""
    modules = {".".join(p.relative_to(root.parent).with_suffix("").parts).removesuffix(".__init__"): p
               for p in sorted(root.rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for module, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                # "from eofnn.sim.atmosphere import anywind" imports the submodule when there is one
                names = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules else node.module
                         for a in node.names]
            else:
                continue
            for name in names:
                while name and name not in modules:
                    name = name.rpartition(".")[0]
                if name and name != module and name != root.name and ALIASES.get(module) != name:
                    graph.setdefault(module, set()).add(name)
    return graph


def test_no_circle_of_imports_between_files():
    """Within a floor too: ``turbulence -> strip -> turbulence`` (a type hint's import) was one."""
    assert cycles(module_graph(Path(__file__).parent.parent / "eofnn")) == []


def test_the_file_circle_check_finds_a_circle(tmp_path):
    root = tmp_path / "eofnn"
    (root / "sim" / "atmosphere").mkdir(parents=True)
    (root / "sim" / "atmosphere" / "a.py").write_text("from eofnn.sim.atmosphere import b\n")
    (root / "sim" / "atmosphere" / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from eofnn.sim.atmosphere.a import X\n")
    (root / "sim" / "c.py").write_text("import eofnn.sim.atmosphere.a\n")
    assert cycles(module_graph(root)) == [["eofnn.sim.atmosphere.a", "eofnn.sim.atmosphere.b",
                                           "eofnn.sim.atmosphere.a"]]
