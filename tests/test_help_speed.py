"""``eofnn --help``, ``--version``, every subcommand's ``--help`` and config errors answer without the heavy imports
(torch, Lightning, HCIPy, scipy, matplotlib: seconds); the subcommands import them only when they run."""

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
    """``eofnn args`` in a fresh interpreter: its exit ``code``, the ``heavy`` modules it imported and its ``stderr``."""
    proc = subprocess.run([sys.executable, "-c", PROBE.format(args=args, heavy=HEAVY)], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    return {**json.loads(proc.stdout.strip().splitlines()[-1]), "stderr": proc.stderr}


@pytest.mark.parametrize("args", [["--help"], ["--version"], [], ["sweep", "--help"]])
def test_help_and_version_import_nothing_heavy(args):
    result = imported(args)
    assert result["heavy"] == [], result
    assert result["code"] in (0, 2)


#: One probe process answers many command lines in turn and says, after each, which heavy modules it has imported by
#: then (the first that lists one is the one that imported it): one interpreter start-up for all of them.
MANY = """
import json, sys
from eofnn.cli.main import main
answers = []
for args in {commands!r}:
    try:
        code = main(args)
    except SystemExit as stop:
        code = stop.code
    answers.append({{"code": code, "heavy": [m for m in {heavy!r} if m in sys.modules]}})
print(json.dumps(answers))
"""
SUBCOMMANDS = ("compare", "fit", "evaluate", "simulate", "stability", "identify", "replay", "export")


def config_errors(folder: Path) -> dict[str, list[str]]:
    """Command lines with a config error the parser or the configs' declarative constraints catch."""
    typo = folder / "typo.yaml"
    typo.write_text("scenario: realistic.yaml\nevaluation: {frames: 1000, setle_frames: 100}\n")
    nested_typo = folder / "nested_typo.yaml"
    nested_typo.write_text("scenario: {grid: {n_across: 10}, atmosphere: {r0: 0.1}}\n"
                           "predictors: {integrator: {controller: integrator}}\n")
    bad_layer = folder / "bad_layer.yaml"
    bad_layer.write_text("scenario: {atmosphere: {layers: [{cn2_fraction: 1.0, wind_speed_mps: -3.0}]}}\n"
                         "predictors: {integrator: {controller: integrator}}\n")
    small = str(ROOT / "configs" / "realistic_small.yaml")
    out = str(folder / "out")
    return {
        "unknown key": ["compare", "--config", str(typo), "--out", out],
        "unknown nested key": ["compare", "--config", str(nested_typo), "--out", out],
        "out of range": ["compare", "--config", small, "--evaluation.frames", "-5", "--out", out],
        "wrong type": ["compare", "--config", small, "--evaluation.frames", "many", "--out", out],
        "unknown controller": ["compare", "--config", small, "--predictors.integrator.controller", "integrater",
                               "--out", out],
        "out of range in a layer": ["compare", "--config", str(bad_layer), "--out", out],
        "out of range in fit": ["fit", "--predictor.history_length", "0", "--out", str(folder / "x.ckpt")],
        "wrong choice in simulate": ["simulate", "--scenario.atmosphere.model", "exactly", "--out",
                                     str(folder / "x.fits")],
        "out of range in training data": ["fit", "--predictor.data.frames", "0", "--out", str(folder / "x.ckpt")],
        "out of range in optimisation": ["fit", "--predictor.optimization.lr", "-1", "--out", str(folder / "x.ckpt")],
    }


@pytest.fixture(scope="module")
def light_answers(tmp_path_factory) -> dict[str, dict]:
    """Each subcommand's ``--help`` and each config error, answered in one process: name -> exit code, heavy modules
    imported by then, and what it printed on stderr (the last lines)."""
    commands = {f"{name} --help": [name, "--help"] for name in SUBCOMMANDS}
    commands.update(config_errors(tmp_path_factory.mktemp("light")))
    proc = subprocess.run([sys.executable, "-c", MANY.format(commands=list(commands.values()), heavy=HEAVY)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    answers = json.loads(proc.stdout.strip().splitlines()[-1])
    errors = [line for line in proc.stderr.splitlines() if line.startswith("eofnn: error:")]
    assert len(errors) == len(commands) - len(SUBCOMMANDS), proc.stderr[-3000:]
    for answer, error in zip(answers[len(SUBCOMMANDS):], errors, strict=True):
        answer["error"] = error
    return dict(zip(commands, answers, strict=True))


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_every_subcommand_help_imports_nothing_heavy(light_answers, name):
    """Building a subcommand's parser (its config dataclasses, their numpydoc, the controllers' names) needs none of
    torch, Lightning, HCIPy, scipy or matplotlib."""
    answer = light_answers[f"{name} --help"]
    assert answer["code"] == 0 and answer["heavy"] == [], answer


@pytest.mark.parametrize("case", ["unknown key", "unknown nested key", "out of range", "wrong type",
                                  "unknown controller", "out of range in a layer", "out of range in fit",
                                  "wrong choice in simulate", "out of range in training data",
                                  "out of range in optimisation"])
def test_a_config_error_answers_before_anything_heavy_is_imported(light_answers, case):
    """An unknown key, a value of the wrong type, out of range or not among the choices stops with one line (exit
    code 2) while torch & co. are still unimported: the config's own checks come before the command's imports."""
    answer = light_answers[case]
    assert answer["code"] == 2 and answer["heavy"] == [], answer
    expected = {"unknown key": "setle_frames", "unknown nested key": "r0", "out of range": "evaluation.frames=-5",
                "wrong type": "many", "unknown controller": "integrater", "out of range in a layer": "wind_speed_mps",
                "out of range in fit": "history_length", "wrong choice in simulate": "exactly",
                "out of range in training data": "frames", "out of range in optimisation": "lr"}[case]
    assert expected in answer["error"], answer


def test_a_lazy_module_imports_on_first_use_and_then_is_the_module_itself():
    """``eofnn.lazy.lazy_module``: nothing imported until an attribute is read; then the holder's name is the real
    module (no stand-in left on the hot path), and introspection of dunders does not import it."""
    code = """
import sys
from eofnn.lazy import LazyModule, lazy_module
colorsys = lazy_module("colorsys")
assert "colorsys" not in sys.modules and isinstance(colorsys, LazyModule)
assert not hasattr(colorsys, "__args__") and "colorsys" not in sys.modules  # introspection is not a use
stand_in = colorsys
assert colorsys.rgb_to_hsv(1.0, 0.0, 0.0) == (0.0, 1.0, 1.0)
assert colorsys is sys.modules["colorsys"] and stand_in.hls_to_rgb is sys.modules["colorsys"].hls_to_rgb
assert lazy_module("colorsys") is sys.modules["colorsys"]  # already imported: the module itself
print("ok")
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.stdout.strip() == "ok", proc.stderr


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
