"""``eofnn --help`` and ``--version`` answer without the heavy imports (torch, Lightning, HCIPy: seconds)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
HEAVY = ("torch", "lightning", "hcipy", "matplotlib", "scipy")
PROBE = """
import json, sys
from eofnn.main import main
try:
    code = main({args!r})
except SystemExit as stop:
    code = stop.code
print(json.dumps({{"code": code, "heavy": [m for m in {heavy!r} if m in sys.modules]}}))
"""


def imported(args: list[str]) -> dict:
    proc = subprocess.run([sys.executable, "-c", PROBE.format(args=args, heavy=HEAVY)], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("args", [["--help"], ["--version"], [], ["sweep", "--help"]])
def test_help_and_version_import_nothing_heavy(args):
    result = imported(args)
    assert result["heavy"] == [], result
    assert result["code"] in (0, 2)


def test_a_subcommand_still_gets_all_its_arguments():
    proc = subprocess.run([sys.executable, "-m", "eofnn.main", "simulate", "--help"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0 and "--scenario.atmosphere.r0_m" in proc.stdout


def test_version_prints_the_package_version():
    import eofnn

    proc = subprocess.run([sys.executable, "-m", "eofnn.main", "--version"], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == f"eofnn {eofnn.__version__}"
