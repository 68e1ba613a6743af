"""eofnn's own configs ship with the package (eofnn/configs/, package data; a checkout's configs/ links to it): they
run by name from any folder, list and copy without replacing a user's file, and CI installs the wheel into a fresh
venv and runs one (scripts/check_wheel.sh, called by .ci/run before the README's test command)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from eofnn.cli.configfile import INSTALLED_CONFIGS, bundled_config, bundled_configs, find_config_file
from eofnn.cli.configs import copy_config, describe, list_configs
from eofnn.cli.main import main

pytestmark = pytest.mark.cli  # most run the command line

ROOT = Path(__file__).resolve().parent.parent


def test_the_checkouts_configs_folder_is_the_packages():
    assert INSTALLED_CONFIGS == ROOT / "eofnn" / "configs"
    assert (ROOT / "configs").is_symlink() and os.readlink(ROOT / "configs") == "eofnn/configs"
    assert (ROOT / "configs" / "realistic_small.yaml").read_text() == (INSTALLED_CONFIGS / "realistic_small.yaml").read_text()
    assert not (INSTALLED_CONFIGS / "__init__.py").exists()  # data, not a floor of the package
    assert {"realistic", "realistic_small", "realistic_sh", "reference", "paper", "tiny"} <= set(bundled_configs())


def test_the_configs_are_package_data():
    tomllib = pytest.importorskip("tomllib")
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert project["tool"]["setuptools"]["package-data"]["eofnn.configs"] == ["*.yaml"]
    assert "eofnn*" in project["tool"]["setuptools"]["packages"]["find"]["include"]


@pytest.mark.parametrize("name, expected", [("realistic_sh", "realistic_sh.yaml"), ("realistic_sh.yaml", "realistic_sh.yaml"),
                                            ("tiny", "tiny.yaml"), ("configs/tiny.yaml", None), ("nothing", None), ("", None)])
def test_a_bundled_config_is_found_by_name_only(name, expected):
    found = bundled_config(name)
    assert (found is None if expected is None else found == INSTALLED_CONFIGS / expected)


def test_a_file_is_read_as_it_is_and_a_name_is_said_in_one_line(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    said: list[str] = []
    (tmp_path / "tiny").write_text("mine")  # a file of the user's, named like one of eofnn's: it is the user's
    assert find_config_file("tiny", say=said.append) == "tiny" and said == []
    assert find_config_file("realistic_sh", say=said.append) == str(INSTALLED_CONFIGS / "realistic_sh.yaml")
    assert said == [f"eofnn: --config 'realistic_sh' -> {INSTALLED_CONFIGS / 'realistic_sh.yaml'} (eofnn's own; "
                    "no such file here)"]
    assert find_config_file("nowhere", say=said.append) == "nowhere" and len(said) == 1


def test_compare_runs_a_bundled_config_by_name_from_any_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        main(["compare", "--config", "realistic_small", "--out", "results/o", "--print_config"])
    assert stop.value.code == 0
    captured = capsys.readouterr()
    assert "n_across: 40" in captured.out  # the bundled config and the bundled scenario it names
    assert captured.err.count("eofnn's own") == 1 and "--config 'realistic_small' ->" in captured.err


def test_a_scenario_is_found_by_name_too(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        main(["simulate", "--scenario", "reference", "--frames", "10", "--out", "runs/r.fits", "--print_config"])
    assert stop.value.code == 0
    captured = capsys.readouterr()
    assert "n_across: 40" in captured.out and "--scenario 'reference' ->" in captured.err


def test_a_name_that_is_nothing_says_where_the_names_are(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["compare", "--config", "realistc_sh", "--out", "o"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "'realistc_sh' does not exist" in err and "eofnn configs list" in err, err


def test_list_names_every_config_with_what_it_is(capsys):
    assert main(["configs", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == list(bundled_configs())
    tiny = next(line for line in lines if line.startswith("tiny "))
    assert "10 actuators across" in tiny and len(tiny) < 130
    assert all(describe(path) for path in bundled_configs().values()), "every config opens with a comment saying what it is"
    assert list_configs() == lines


def test_copy_gives_a_file_of_ones_own_and_never_replaces_one(tmp_path, capsys):
    assert main(["configs", "copy", "realistic_small", str(tmp_path / "mine")]) == 0
    copy = tmp_path / "mine" / "realistic_small.yaml"
    assert copy.read_text() == (INSTALLED_CONFIGS / "realistic_small.yaml").read_text()
    err = capsys.readouterr().err
    assert "scenario 'realistic.yaml' is eofnn's own" in err and "eofnn configs copy realistic" in err
    copy.write_text("# edited\n")
    assert main(["configs", "copy", "realistic_small.yaml", str(tmp_path / "mine")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "exists: eofnn never replaces your file" in err, err
    assert copy.read_text() == "# edited\n"
    with pytest.raises(Exception, match="exists"):
        copy_config("realistic_small", tmp_path / "mine")


@pytest.mark.parametrize("args, message", [
    (["configs", "copy", "nothing", "x"], "'nothing' is not one of eofnn's configs: antialias_sh_small"),
    (["configs", "copy"], "eofnn configs copy needs a NAME"),
    (["configs", "list", "tiny"], "eofnn configs list takes no NAME"),
    (["configs", "paste"], "invalid choice: 'paste'"),
])
def test_bad_configs_commands_are_one_line(args, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert list(tmp_path.iterdir()) == []


def test_copy_into_a_file_is_refused(tmp_path):
    (tmp_path / "f").write_text("")
    with pytest.raises(Exception, match="is a file, not a folder"):
        copy_config("tiny", tmp_path / "f")


def test_ci_checks_the_wheel_before_the_readmes_test_command():
    steps = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line and not line.startswith("#")]
    assert "set -euo pipefail" in steps and "bash scripts/check_wheel.sh" in steps
    assert steps.index("bash scripts/setup.sh") < steps.index("bash scripts/check_wheel.sh") < len(steps) - 1
    readme = (ROOT / "README.md").read_text()
    assert steps[-1] in readme, "the last step of .ci/run is the README's test command"
    script = (ROOT / "scripts" / "check_wheel.sh").read_text()
    assert "set -euo pipefail" in script and "--config tiny" in script and "venv" in script


def test_the_wheel_check_script_parses():
    done = subprocess.run(["bash", "-n", str(ROOT / "scripts" / "check_wheel.sh")], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(bundled_configs()))
def test_every_bundled_config_parses_by_name(name, tmp_path, monkeypatch, capsys):
    import yaml

    monkeypatch.chdir(tmp_path)  # no checkout around: the name alone finds it
    keys = set(yaml.safe_load(bundled_configs()[name].read_text()))
    if keys & {"grid", "atmosphere"}:  # a scenario
        args = ["simulate", "--scenario", name, "--frames", "10", "--out", "runs/x.fits"]
    else:
        args = ["evaluate" if "checkpoints" in keys else "compare", "--config", name, "--out", "results/x"]
    with pytest.raises(SystemExit) as stop:
        main([*args, "--print_config"])
    assert stop.value.code == 0, capsys.readouterr().err
    assert "n_across:" in capsys.readouterr().out


@pytest.mark.slow
def test_the_wheel_holds_every_bundled_config(tmp_path):
    """The wheel built from the files git would commit holds eofnn/configs/*.yaml (the full install-and-run check is
    CI's scripts/check_wheel.sh)."""
    import shutil
    import sys
    import zipfile

    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, text=True)
    if files.returncode != 0:
        pytest.skip("not a git checkout")
    source = tmp_path / "src"
    for name in files.stdout.splitlines():
        path = ROOT / name
        if name.startswith(("eofnn/", "pyproject.toml", "README.md")) and path.is_file() and not path.is_symlink():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, source / name)
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                            str(tmp_path / "dist"), str(source)], capture_output=True, text=True)
    assert built.returncode == 0, built.stderr[-2000:]
    wheel = next((tmp_path / "dist").glob("eofnn-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {f"eofnn/configs/{p.name}" for p in INSTALLED_CONFIGS.glob("*.yaml")} <= names
    assert "eofnn/cli/configs.py" in names


def test_an_inline_value_is_never_taken_for_a_name():
    inline = "{grid: {n_across: 8, diameter_m: 2.0}, atmosphere: {r0_m: 0.1}}" + " " * 400  # longer than a file name
    assert find_config_file(inline, "--scenario", say=pytest.fail) == inline
