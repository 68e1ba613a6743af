"""The test tiers (docs/usage.md, "Test tiers") hold: every test that runs the command line or another process is marked
``cli``, every mark a test module sets is registered, and every module keeps a test in the fast tier (``-m "not slow"``).

Read from the test files' syntax trees: a test runs the command line when it, a helper function of its module, or a
fixture it asks for (its module's or conftest.py's) calls ``main``, ``console`` or ``build_parser``, or anything of
``subprocess``.
"""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent
MODULES = sorted(TESTS.glob("test_*.py"))
ENTRY_POINTS = {"main", "console", "build_parser"}  # eofnn's command line, an example's or a benchmark's main
TIERS = {"physics", "cli", "slow"}
#: Modules with no fast test: one benchmark run that every test reads (12 s), one Pareto comparison (8 s), and real
#: Ctrl-C's to eofnn in subprocesses (1.4 s to 11 s each).
ALL_SLOW = {"test_benchmarks_smoke.py", "test_pareto.py", "test_interrupt.py"}


def mark_names(node: ast.expr) -> set[str]:
    """The names X of ``pytest.mark.X`` and ``pytest.mark.X(...)`` in a decorator or a ``pytestmark`` value."""
    if isinstance(node, (ast.List, ast.Tuple)):
        return set().union(*(mark_names(e) for e in node.elts))
    if isinstance(node, ast.Call):
        node = node.func
    if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute) and node.value.attr == "mark"
            and isinstance(node.value.value, ast.Name) and node.value.value.id == "pytest"):
        return {node.attr}
    return set()


def module_marks(tree: ast.Module) -> set[str]:
    marks: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets):
            marks |= mark_names(node.value)
    return marks


def functions(tree: ast.Module) -> dict[str, ast.FunctionDef]:
    return {node.name: node for node in tree.body if isinstance(node, ast.FunctionDef)}


def entry_points(tree: ast.Module) -> set[str]:
    """:data:`ENTRY_POINTS` and the module's own names for them (``real_main = eofnn.cli.main.main``)."""
    names = set(ENTRY_POINTS)
    for node in tree.body:
        value = node.value if isinstance(node, ast.Assign) else None
        if (isinstance(value, ast.Name) and value.id in ENTRY_POINTS) or (
                isinstance(value, ast.Attribute) and value.attr in ENTRY_POINTS):
            names |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    return names


def calls_a_command_line(node: ast.AST, names: set[str]) -> bool:
    """Whether ``node`` itself calls one of ``names`` or subprocess (helpers and fixtures: :func:`cli_functions`)."""
    for call in ast.walk(node):
        if not isinstance(call, ast.Call):
            continue
        f = call.func
        if isinstance(f, ast.Name) and f.id in names:
            return True
        if isinstance(f, ast.Attribute) and (f.attr in names or
                                             (isinstance(f.value, ast.Name) and f.value.id == "subprocess")):
            return True
    return False


def cli_functions(defs: dict[str, ast.FunctionDef], known: set[str], names: set[str] = ENTRY_POINTS) -> set[str]:
    """The functions of ``defs`` that run a command line, directly, through another such function (called, or asked
    for as a fixture by its parameter name), or through one in ``known`` (conftest.py's)."""
    found = set(known)
    changed = True
    while changed:
        changed = False
        for name, fn in defs.items():
            if name in found:
                continue
            params = {a.arg for a in fn.args.args + fn.args.kwonlyargs}
            called = {c.func.id for c in ast.walk(fn) if isinstance(c, ast.Call) and isinstance(c.func, ast.Name)}
            if calls_a_command_line(fn, names) or (params | called) & found:
                found.add(name)
                changed = True
    return found


CONFTEST_CLI = cli_functions(functions(ast.parse((TESTS / "conftest.py").read_text())), set())


def marks_and_cli(path: Path) -> tuple[set[str], dict[str, tuple[set[str], bool]]]:
    """A module's own marks, and for each test its marks (its own and the module's) and whether it runs a command
    line."""
    tree = ast.parse(path.read_text())
    defs = functions(tree)
    cli = cli_functions(defs, CONFTEST_CLI, entry_points(tree))
    own = module_marks(tree)
    tests = {name: (own | set().union(*(mark_names(d) for d in fn.decorator_list)), name in cli)
             for name, fn in defs.items() if name.startswith("test_")}
    return own, tests


def test_the_conftest_cli_fixtures_are_seen_as_command_lines():
    assert {"cli", "cli_error"} <= CONFTEST_CLI
    tree = ast.parse("import subprocess\nimport eofnn.cli.main\nalias = eofnn.cli.main.main\n"
                     "def helper():\n    subprocess.run(['x'])\n"
                     "def fixture_like(helper_user):\n    return 1\n"
                     "def helper_user():\n    helper()\n"
                     "def test_a(fixture_like):\n    pass\n"
                     "def test_b(cli_error):\n    pass\n"
                     "def test_c():\n    return 2\n"
                     "def test_d():\n    alias(['--help'])\n")
    found = cli_functions(functions(tree), CONFTEST_CLI, entry_points(tree))
    assert {"helper", "helper_user", "fixture_like", "test_a", "test_b", "test_d"} <= found and "test_c" not in found


def test_every_test_that_runs_a_command_line_is_marked_cli():
    unmarked = [f"{path.name}::{name}" for path in MODULES
                for name, (marks, runs_cli) in marks_and_cli(path)[1].items() if runs_cli and "cli" not in marks]
    assert not unmarked, f"these run the command line or a subprocess but are not marked cli: {unmarked}"


def test_every_mark_is_registered_and_every_module_keeps_a_fast_test(request):
    registered = {line.split(":")[0].strip() for line in request.config.getini("markers")}
    assert TIERS <= registered
    builtin = {"parametrize", "skip", "skipif", "xfail", "usefixtures", "filterwarnings"}
    problems = []
    for path in MODULES:
        own, tests = marks_and_cli(path)
        used = own.union(*(marks for marks, _ in tests.values()))
        if used - registered - builtin:
            problems.append(f"{path.name}: unregistered marks {sorted(used - registered - builtin)}")
        has_fast = any("slow" not in marks for marks, _ in tests.values())
        if has_fast == (path.name in ALL_SLOW):
            problems.append(f"{path.name}: {'a' if has_fast else 'no'} test in the fast tier")
    assert not problems, problems
