"""No silent surprises in config files: a misspelt key is refused naming its file, its line and the nearest allowed
key; a scenario name found in eofnn's own configs rather than beside the user's config is said in one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from eofnn.cli.configfile import check_config_keys
from eofnn.errors import ConfigError

pytestmark = pytest.mark.cli

CONF = Path(__file__).parent / "conf"
ROOT = Path(__file__).resolve().parent.parent


def _copy(name: str, folder: Path, old: str = "", new: str = "") -> Path:
    """``tests/conf/name`` copied into ``folder``, ``old`` replaced by ``new`` (once, and it must be there)."""
    text = (CONF / name).read_text()
    assert old in text
    path = folder / name
    path.write_text(text.replace(old, new, 1))
    return path


def _line_of(path: Path, text: str) -> int:
    return next(n for n, line in enumerate(path.read_text().splitlines(), 1) if text in line)


def test_a_misspelt_key_in_a_config_names_the_file_its_line_and_the_nearest_key(cli_error, tmp_path):
    config = _copy("tiny_evaluate.yaml", tmp_path, "settle_frames:", "settle_frame:")
    _copy("tiny_scenario.yaml", tmp_path)
    line = _line_of(config, "settle_frame:")
    error = cli_error(["evaluate", "--config", config, "--baselines", "[integrator]", "--out", tmp_path / "o"],
                      f"config file {str(config)!r}, line {line}: unknown key 'settle_frame' in evaluation: "
                      "did you mean 'settle_frames'?", tmp_path / "o")
    assert "does not accept" not in error


def test_a_misspelt_key_in_a_scenario_file_a_config_names_is_found_in_that_file(cli_error, tmp_path):
    config = _copy("tiny_evaluate.yaml", tmp_path)
    scenario = _copy("tiny_scenario.yaml", tmp_path, "r0_wavelength_m:", "r0_wavelenght_m:")
    cli_error(["evaluate", "--config", config, "--baselines", "[integrator]", "--out", tmp_path / "o"],
              f"tiny_scenario.yaml', line {_line_of(scenario, 'r0_wavelenght_m')}: unknown key 'r0_wavelenght_m' in "
              "scenario.atmosphere: did you mean 'r0_wavelength_m'?", tmp_path / "o")


def test_a_misspelt_key_in_a_scenario_file_on_the_command_line(cli_error, tmp_path):
    scenario = _copy("tiny_scenario.yaml", tmp_path, "frame_rate_hz:", "frame_rate:")
    cli_error(["simulate", "--scenario", scenario, "--out", tmp_path / "run.fits"],
              f"config file {str(scenario)!r}, line {_line_of(scenario, 'frame_rate:')}: unknown key 'frame_rate' in "
              "scenario: did you mean 'frame_rate_hz'?", tmp_path / "run.fits")


def test_a_misspelt_key_inside_a_predictor_and_at_the_top_level(cli_error, tmp_path):
    _copy("tiny_scenario.yaml", tmp_path)
    config = _copy("tiny_compare.yaml", tmp_path, "history_length: 5", "histroy_length: 5")
    cli_error(["compare", "--config", config, "--out", tmp_path / "o"],
              f"line {_line_of(config, 'histroy_length')}: unknown key 'histroy_length' in predictors.cl_eof: "
              "did you mean 'history_length'?", tmp_path / "o")
    config = _copy("tiny_compare.yaml", tmp_path, "evaluation:", "evalution:")
    cli_error(["compare", "--config", config, "--out", tmp_path / "o"],
              "unknown key 'evalution' at the top level: did you mean 'evaluation'?", tmp_path / "o")


@pytest.mark.parametrize("text, expected", [
    # A list of dataclasses (layers), through a nested mapping: line 3 of the file.
    ("scenario:\n  atmosphere:\n    layers: [{cn2_fraction: 1.0, wind_speed: 3.0}]\n",
     "line 3: unknown key 'wind_speed' in scenario.atmosphere.layers: did you mean 'wind_speed_mps'?"),
    # A YAML merge key brings its mapping's keys in: they are checked where they land.
    ("defaults: &d {frames: 100, setle_frames: 10}\n", "line 1: unknown key 'defaults' at the top level"),
    ("evaluation:\n  <<: {frames: 100}\n  setle_frames: 10\n", "line 3: unknown key 'setle_frames' in evaluation"),
    # A scenario's plant changes: the plant's fields.
    ("scenarios:\n  nominal: {}\n  doubled: {dm_gian: 2.0}\n",
     "line 3: unknown key 'dm_gian' in scenarios.doubled: did you mean 'dm_gain'?"),
    # Nothing close: the allowed keys are listed.
    ("evaluation: {zzz: 1}\n", "unknown key 'zzz' in evaluation: allowed are analytic_stability, divergence_factor,"),
])
def test_keys_are_checked_against_the_configuration_dataclasses(tmp_path, text, expected):
    from eofnn.cli.compare import EvaluateConfig

    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=None) as info:
        check_config_keys(path, EvaluateConfig)
    assert expected in str(info.value) and str(path) in str(info.value), info.value


def test_free_mappings_and_known_keys_pass(tmp_path):
    from eofnn.cli.compare import CompareConfig, EvaluateConfig

    path = tmp_path / "c.yaml"
    path.write_text("config: other.yaml\nscenarios: {a: {dm_gain: 2.0}, b: {}}\npredictors:\n  n: {network: {class_path: "
                    "x.Y, init_args: {whatever: 2}}, optimization: {search: {lr: [1.0]}}}\n"
                    "evaluation:\n  <<: {frames: 100}\n  settle_frames: 10\n")
    check_config_keys(path, CompareConfig)
    for name in ["realistic_small.yaml", "paper.yaml", "elt_scao.yaml", "classical_small.yaml", "vibrations.yaml"]:
        check_config_keys(ROOT / "configs" / name, CompareConfig)
    check_config_keys(ROOT / "configs" / "evaluate.yaml", EvaluateConfig)


def test_a_scenario_taken_from_eofnns_configs_is_said_in_one_line(cli, tmp_path):
    copy = tmp_path / "mine.yaml"
    copy.write_text((ROOT / "configs" / "realistic_small.yaml").read_text())  # names scenario: realistic.yaml
    _, err = cli("compare", "--config", copy, "--out", tmp_path / "o", "--evaluation.frames", "-1")
    said = [line for line in err.splitlines() if "realistic.yaml" in line]
    assert said == [f"eofnn: scenario 'realistic.yaml' -> {ROOT / 'eofnn' / 'configs' / 'realistic.yaml'} (eofnn's own; none "
                    f"beside your config {str(copy)!r})"], err
    # Beside the config, the file is the one its reader looks for: nothing is said.
    (tmp_path / "realistic.yaml").write_text((ROOT / "configs" / "realistic.yaml").read_text())
    _, err = cli("compare", "--config", copy, "--out", tmp_path / "o", "--evaluation.frames", "-1")
    assert "eofnn's own" not in err and len(err.strip().splitlines()) == 1, err
