"""``eofnn --help`` and ``--version`` answer without the heavy imports (torch, Lightning, HCIPy: seconds)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.cli

ROOT = Path(__file__).resolve().parent.parent
HEAVY = ("torch", "lightning", "hcipy", "matplotlib", "scipy")
PROBE = """
import json, sys
from eofnn.cli.main import main
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


@pytest.mark.slow
def test_a_subcommand_still_gets_all_its_arguments():
    proc = subprocess.run([sys.executable, "-m", "eofnn.cli.main", "simulate", "--help"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0 and "--scenario.atmosphere.r0_m" in proc.stdout


def test_version_prints_the_package_version():
    import eofnn

    proc = subprocess.run([sys.executable, "-m", "eofnn.cli.main", "--version"], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == f"eofnn {eofnn.__version__}"


@pytest.fixture(scope="module")
def fit_help() -> str:
    from eofnn.cli.commands import build_parser

    return build_parser(["fit"])._subcommands_action.choices["fit"].format_help()


def option_help(text: str, option: str) -> str:
    """The help paragraph of one option in a ``--help`` text, on one line."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().startswith(option + " "))
    body = []
    for line in lines[start + 1:]:
        if line.strip().startswith("--") or not line.startswith(" " * 8):
            break
        body.append(line.strip())
    return " ".join(body)


def test_controller_help_lists_every_registered_controller(fit_help):
    from eofnn.control.registry import controller_names

    text = option_help(fit_help, "--predictor.controller")
    assert all(name in text for name in controller_names()), text
    assert "dithered_integrator" in text


def test_units_and_values_are_in_the_help(fit_help):
    from eofnn.sim.atmosphere.turbulence import MODELS

    assert "actuator pitches" in option_help(fit_help, "--scenario.plant.misregistration_x")
    assert "actuator pitches" in option_help(fit_help, "--scenario.plant.misregistration_y")
    model = option_help(fit_help, "--scenario.atmosphere.model")
    assert all(name in model for name in MODELS), model


def test_help_shows_no_sphinx_markup(fit_help):
    from eofnn.cli.commands import plain_text

    assert plain_text("a :class:`~eofnn.sim.atmosphere.disturbances.Vibration` or "
                      ":mod:`eofnn.sim.atmosphere.changes`, ``x``") == "a Vibration or eofnn.sim.atmosphere.changes, x"
    for markup in (":class:", ":mod:", ":attr:", ":func:", "``"):
        assert markup not in fit_help, markup
