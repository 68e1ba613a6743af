"""docs/design.md matches the code: the floors it lists are those tests/test_layering.py enforces, every path it names
exists, and nothing in the repository links outside it."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from test_layering import BASE, FLOORS, STANDALONE

ROOT = Path(__file__).resolve().parent.parent
DESIGN = ROOT / "docs" / "design.md"


def design_floors(text: str) -> list[str]:
    """The numbered list after the ``<!-- floors -->`` marker, bottom floor first."""
    block = text.split("<!-- floors:", 1)[1].split("\n\n", 1)[0]
    return re.findall(r"^\d+\. `(\w+)`$", block, flags=re.M)


def test_the_floors_of_the_design_are_the_floors_the_layering_test_enforces():
    text = DESIGN.read_text()
    assert design_floors(text) == FLOORS
    for leaf in BASE | STANDALONE:
        assert f"`{leaf}`" in text, f"docs/design.md does not name the leaf module {leaf!r}"


def test_every_folder_of_the_package_is_a_floor_of_the_design():
    folders = {p.name for p in (ROOT / "eofnn").iterdir() if (p / "__init__.py").exists()}
    assert folders == set(design_floors(DESIGN.read_text()))


@pytest.mark.cli
def test_every_path_the_design_names_exists():
    paths = set(re.findall(r"`((?:eofnn|tests|experiments|docs|configs|benchmarks|examples)/[\w./-]*)`",
                           DESIGN.read_text()))
    assert paths, "the design names no paths"
    missing = sorted(p for p in paths if not (ROOT / p).exists() and not _ignored(p))
    assert missing == []


def _ignored(path: str) -> bool:
    """An output folder git ignores (``experiments/runs/``): named by the design, made by the scripts, not in a clone."""
    return subprocess.run(["git", "check-ignore", "-q", path], cwd=ROOT).returncode == 0


@pytest.mark.cli
def test_the_readme_links_the_design_and_nothing_links_outside_the_repository():
    assert "docs/design.md" in (ROOT / "README.md").read_text()
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    outside = [name for name in tracked
               if name.endswith((".md", ".py", ".yaml", ".sh", ".toml", ".txt", ".cfg")) and (ROOT / name).is_file()
               and re.search(r"\.\./shared|\]\(\.\./", (ROOT / name).read_text(errors="replace"))
               and name != "tests/test_design.py"]
    assert outside == []


#: Files whose text still cites an issue, each owned by a branch that removes it: the entry goes when it lands.
STILL_CITES_AN_ISSUE: set[str] = set()


def test_no_file_of_the_package_cites_an_issue():
    """The library says what it does and why; an issue number is the project's history, which goes stale there
    (the measured findings behind its choices: docs/findings.md)."""
    cites = re.compile(r"\bissues? #?\d+|#\d{2,}\b", re.IGNORECASE)
    found = {str(path.relative_to(ROOT)) for path in sorted((ROOT / "eofnn").rglob("*.py")) if cites.search(path.read_text())}
    assert found <= STILL_CITES_AN_ISSUE, sorted(found - STILL_CITES_AN_ISSUE)
    assert cites.search("as issue 30 asked") and cites.search("see #44") and not cites.search("color='#1f77b4'")
