"""The README's commands, as written, so that they cannot rot: every command of the README and of its reference page
(docs/usage.md) parses (configs found, keys known, values valid), and the telemetry recipe runs end to end in order,
at short sizes on a small telescope."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from eofnn.cli.commands import COMMANDS, build_parser
from eofnn.cli.main import main

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()
#: The README's reference page: the commands and options the README leaves out to stay short.
USAGE = (ROOT / "docs" / "usage.md").read_text()
TELEMETRY_SECTION = "## From telemetry alone"
#: Short sizes for the telemetry recipe: a 2 m telescope, 10 actuators across, a few thousand frames.
SMALL = {"--frames 20000": "--frames 3000", "--frames 5000": "--frames 800"}
COMMAND_START = re.compile(rf"(^|\s|/)eofnn +(({'|'.join(COMMANDS)})(\s|$)|--)")
SMALL_SCENARIO = ["--scenario.grid.n_across", "10", "--scenario.grid.diameter_m", "2.0"]


def commands(text: str) -> list[list[str]]:
    """Every ``eofnn ...`` command of the indented code blocks of ``text``, continuation lines joined."""
    found, pending = [], ""
    for line in text.splitlines():
        starts = line.startswith("    ") and COMMAND_START.search(line.strip()) is not None
        if not pending and not starts:
            continue
        pending += " " + line.strip()
        if pending.endswith("\\"):
            pending = pending[:-1]
            continue
        words = shlex.split(pending, comments=True)
        pending = ""
        for i, word in enumerate(words):
            if (word == "eofnn" or word.endswith("/eofnn")) and i + 1 < len(words):
                found.append(words[i + 1:])
                break
    return found


def section(title: str) -> str:
    start = README.index(title)
    end = README.find("\n## ", start + len(title))
    return README[start:end if end > 0 else None]


ALL = commands(README) + commands(USAGE)


def test_the_readme_has_commands_to_check():
    names = {c[0] for c in ALL if c and not c[0].startswith("-")}
    assert {"compare", "evaluate", "fit", "simulate", "sweep", "stability", "identify", "replay", "export"} <= names


@pytest.mark.cli
@pytest.mark.parametrize("args", [c for c in ALL if c and c[0] != "--help" and "--help" not in c],
                         ids=lambda c: " ".join(c)[:60])
def test_every_readme_command_parses(args, monkeypatch):
    monkeypatch.chdir(ROOT)
    parser = build_parser([args[0]])
    cfg = parser.parse_args(args)
    if args[0] == "sweep":
        assert Path(cfg.sweep.config).is_file() and Path(cfg.sweep.grid).is_file()
    else:
        parser.instantiate(cfg)
    out = getattr(cfg[args[0]], "out", None)
    if out is not None:  # results never land in the repository's tracked files
        assert out.split("/")[0] in ("results", "runs") or out.startswith("experiments/"), out


@pytest.mark.cli
@pytest.mark.slow
def test_the_telemetry_recipe_runs_in_order(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    recipe = section(TELEMETRY_SECTION)
    for old, new in SMALL.items():
        assert old in recipe, f"the README's telemetry recipe changed: update SMALL ({old!r})"
        recipe = recipe.replace(old, new)
    steps = commands(recipe)
    assert [s[0] for s in steps] == ["simulate", "simulate", "identify", "fit", "replay", "export"]
    for args in steps:
        if args[0] == "simulate":
            args = [*args, *SMALL_SCENARIO]
        code = main(args)
        err = capsys.readouterr().err
        assert code == 0, f"eofnn {' '.join(args)}: {err}"
    for path in re.findall(r"--out (\S+)", recipe):
        assert (tmp_path / path).exists(), path
