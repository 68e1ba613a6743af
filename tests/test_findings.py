"""The findings table: experiments/README.md opens with it, computed from the committed summaries (a summary that
changes changes the table), and the project's README shows the same rows, short enough to read in a minute."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXPERIMENTS = ROOT / "experiments"
README = (ROOT / "README.md").read_text()


def _table(page: str = "") -> list[str]:
    done = subprocess.run([sys.executable, "-c", f"from report_findings import findings_table; "
                           f"print(findings_table({page!r}))"], cwd=EXPERIMENTS, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()


def _table_of(text: str, heading: str) -> list[str]:
    block = text.split(heading, 1)[1].split("\n## ", 1)[0]
    return [line for line in block.splitlines() if line.startswith("|")]


@pytest.mark.cli
def test_the_experiments_page_opens_with_the_findings_table():
    page = (EXPERIMENTS / "README.md").read_text()
    assert re.findall(r"^## .*", page, flags=re.M)[0] == "## Findings"
    assert _table_of(page, "## Findings") == _table()


@pytest.mark.cli
def test_the_readme_shows_the_same_findings_with_the_flagship_first():
    rows = _table_of(README, "## What it found")
    generated = _table("experiments/README.md")
    assert rows == generated
    assert "flagship" in rows[2].lower()  # the first finding is the README's first command's
    assert len(rows) - 2 <= 8  # at most 8 findings
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        from report_findings import anchor
    finally:
        sys.path.remove(str(EXPERIMENTS))
    anchors = {anchor(h) for h in re.findall(r"^## (.*)", (EXPERIMENTS / "README.md").read_text(), flags=re.M)}
    for row in generated[2:]:
        assert re.search(r"^\| [^|]+ \| \d[\d.]*x", row), f"a finding without its plain ratio first: {row[:80]}"
        link = re.search(r"\]\(experiments/README.md#([\w-]+)\) \|$", row)
        assert link and link.group(1) in anchors, row[-120:]


@pytest.mark.cli
def test_the_table_is_computed_from_the_summaries(tmp_path):
    copy = tmp_path / "experiments"
    shutil.copytree(EXPERIMENTS, copy, ignore=shutil.ignore_patterns("runs", "*.png"))
    summary = copy / "realistic_sh" / "summary.json"
    data = json.loads(summary.read_text())
    data["metrics"]["scenarios"]["nominal"]["integrator"]["median_rms_nm"] *= 1.1  # the integrator 10% worse
    summary.write_text(json.dumps(data))
    done = subprocess.run([sys.executable, "-c", "from report_findings import sh_row; print(sh_row()['number'])"],
                          cwd=copy, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("1.16x"), done.stdout  # 0.96 x 1.1 squared


def test_the_readme_is_short_and_opens_with_what_and_how_to_install():
    lines = README.splitlines()
    assert len(lines) < 150
    first_screen = "\n".join(lines[:40])
    assert "## Install" in first_screen and "pip install" in first_screen and "bash scripts/setup.sh" in first_screen
    assert not re.search(r"\b[0-9a-f]{7,40}\b", README), "no commit hashes in the README"


@pytest.mark.cli
def test_a_goal_is_met_only_as_strongly_as_the_realisations_say():
    code = ("from report_oopao import _verdict; "
            "print(_verdict(1.55, [1.48, 1.61, 1.56], 1.5)); print(_verdict(1.8, [1.78, 1.82], 1.5)); "
            "print(_verdict(1.4, [1.3, 1.5], 1.5))")
    done = subprocess.run([sys.executable, "-c", code], cwd=EXPERIMENTS, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    thin, every, missed = done.stdout.strip().splitlines()
    assert "not on every realisation" in thin and "1 of 3 below" in thin
    assert every.strip() == "(met on every realisation)"
    assert missed.strip() == "(not met)"
