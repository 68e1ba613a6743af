"""A corpus of bad inputs, class by class (issue: every bad input gets one line): each ends with exit code 2,
one line that names the value, no traceback, nothing run and nothing a user wrote changed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from eofnn.cli.main import main

CONF = Path(__file__).parent / "conf"
TINY = CONF / "tiny_compare.yaml"

# Every numeric field a user sets, with the key it has on the command line.
NUMERIC_KEYS = [
    "scenario.atmosphere.r0_m", "scenario.atmosphere.r0_wavelength_m", "scenario.atmosphere.outer_scale_m",
    "scenario.frame_rate_hz", "scenario.grid.diameter_m", "scenario.grid.obstruction", "scenario.plant.dm_gain",
    "scenario.plant.wfs_noise_nm", "scenario.plant.wfs_gain", "scenario.plant.misregistration_x",
    "scenario.plant.nonlinearity_scale_nm", "predictors.ol_eof.optimization.alpha", "predictors.ol_eof.optimization.lr",
    "predictors.cl_eof.data.dither_nm", "predictors.cl_eof.data.integrator_gain", "predictors.integrator.gain",
    "predictors.ol_eof.dm_gain_model", "evaluation.strehl_wavelength_m", "evaluation.divergence_factor",
]
NON_FINITE = [".inf", "-.inf", ".nan", "null"]


# null is allowed for dm_gain_model (the predictor's own DM model), alpha (chosen on validation data) and lr (the
# optimiser's default), so those pairs are not bad inputs.
CASES = [(key, value) for key in NUMERIC_KEYS for value in NON_FINITE
         if not (value == "null" and key.endswith(("dm_gain_model", "alpha", ".lr")))]


@pytest.mark.cli
@pytest.mark.parametrize("key, value", CASES)
def test_non_finite_and_null_values(cli_error, tmp_path, key, value):
    cli_error(["compare", "--config", TINY, f"--{key}={value}", "--out", tmp_path / "o"], key.rsplit(".", 1)[-1],
              tmp_path / "o")


@pytest.mark.cli
@pytest.mark.parametrize("layer", ["{cn2_fraction: .inf}", "{wind_speed_mps: .nan}", "{wind_direction_deg: .inf}",
                                   "{wind_direction_deg: .nan}", "{wind_speed_mps: .inf}", "{cn2_fraction: -1}",
                                   "{wind_speed_mps: 'fast'}", "{speed: 3}"])
def test_bad_layers(cli_error, tmp_path, layer):
    key = layer.strip("{}").split(":")[0]
    cli_error(["compare", "--config", TINY, "--scenario.atmosphere.layers", f"[{layer}]", "--out", tmp_path / "o"],
              key, tmp_path / "o")


@pytest.mark.cli
@pytest.mark.parametrize("changes, expected", [
    ({"dm_gain": "two"}, "dm_gain='two'"), ({"dm_gain": [0.1]}, "dm_gain=[0.1]"), ({"dm_gain": True}, "dm_gain=True"),
    ({"dm_gain": None}, "dm_gain=None"), ({"wfs_noise_nm": "1 nm"}, "wfs_noise_nm='1 nm'"),
    ({"nonlinearity": 3}, "nonlinearity=3"), ({"delay_frames": 0.5}, "delay_frames=0.5"),
    ({"dm_gian": 2.0}, "unknown model error 'dm_gian'"), ({"dm_gain": float("inf")}, "dm_gain=inf"),
])
def test_wrong_types_in_scenario_variants(cli_error, tmp_path, changes, expected):
    cli_error(["compare", "--config", TINY, "--scenarios", json.dumps({"bad": changes}).replace("Infinity", ".inf"),
               "--out", tmp_path / "o"], expected, tmp_path / "o")


@pytest.mark.cli
@pytest.mark.parametrize("args, expected", [
    (["--scenario.plant.dm_gain", "two"], "dm_gain"),
    (["--evaluation.frames", "1.5"], "frames"),
    (["--predictors.ol_eof.history_length", "2.5"], "history_length"),
    (["--predictors.ol_eof.history", "sideways"], "history='sideways'"),
    (["--scenarios", "[1, 2]"], "scenarios"),
    (["--scenarios", "{x: 3}"], "scenarios"),
    (["--predictors.ol_eof.network", "{class_path: 3}"], "class_path=3"),
    (["--predictors.ol_eof.network", "{class_path: MLP, init_args: [1]}"], "predictors"),
    (["--predictors.ol_eof.network", "{class_path: no.such.Module}"], "cannot be imported"),
    (["--predictors.ol_eof.controller", "smith_predictor"], "controller"),
    (["--predictors.ol_eof.optimization.fit_method", "magic"], "fit_method"),
    (["--predictors.integrator.leak", "2"], "leak=2"),
])
def test_wrong_types_and_choices(cli_error, tmp_path, args, expected):
    cli_error(["compare", "--config", TINY, *args, "--out", tmp_path / "o"], expected, tmp_path / "o")


@pytest.mark.cli
@pytest.mark.parametrize("args, expected", [
    (["--scenario.grid.obstruction", "0.97"], "obstruction=0.97"),
    (["--scenario.grid.obstruction", "1.0"], "obstruction=1.0"),
    (["--scenario.grid.obstruction", "-0.1"], "obstruction=-0.1"),
    (["--scenario.grid.diameter_m", "0"], "diameter_m=0"),
    (["--scenario.grid.diameter_m", "-8"], "diameter_m=-8"),
    (["--scenario.grid.n_across", "1"], "n_across=1"),
    (["--scenario.frame_rate_hz", "0"], "frame_rate_hz=0"),
    (["--scenario.plant.delay_frames", "0"], "delay_frames=0"),
])
def test_impossible_geometry_and_timing(cli_error, tmp_path, args, expected):
    cli_error(["compare", "--config", TINY, *args, "--out", tmp_path / "o"], expected, tmp_path / "o")


@pytest.mark.cli
@pytest.mark.parametrize("args, expected", [
    (["--scenario.grid.n_across", "100000"], "n_across=100000"),
    (["--evaluation.frames", str(10**12)], "frames=1000000000000"),
    (["--evaluation.realisations", str(10**6)], "realisations=1000000"),
    (["--predictors.ol_eof.data.frames", str(10**12)], "frames=1000000000000"),
    (["--predictors.ol_eof.data.sequence_frames", str(10**9)], "sequence_frames=1000000000"),
    (["--predictors.ol_eof.history_length", str(10**6)], "history_length=1000000"),
    (["--scenario.grid.n_across", "512", "--evaluation.realisations", "1024"], "of memory"),
    (["--scenario.grid.n_across", "512", "--predictors.ol_eof.data.realisations", "1024"], "of memory"),
    (["--scenario.grid.n_across", "40", "--evaluation.frames", "10000000", "--evaluation.realisations", "4"],
     "--allow_long true"),
])
def test_sizes_that_cannot_fit_are_refused_up_front(cli_error, tmp_path, args, expected):
    cli_error(["compare", "--config", TINY, *args, "--out", tmp_path / "o"], expected, tmp_path / "o")


def _alias_bomb(levels: int = 7) -> str:
    lines = ['a0: &a0 ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]")
    return "\n".join(lines) + "\n"


@pytest.mark.cli
@pytest.mark.parametrize("content, expected", [
    (_alias_bomb(), "YAML nodes"),
    (bytes(range(256)) * 8, "not text"),
    ("predictors: [unclosed\n", "not valid YAML"),
    ("scenario: !!python/object/apply:os.system ['echo hi']\n", "python/object/apply:os.system is refused"),
    ("scenario: {grid: {n_across: 8}}\npredictors: {x: {controller: uncorrected}}\nsurprise: 1\n", "surprise"),
])
def test_unreadable_or_hostile_config_files(cli_error, tmp_path, content, expected):
    path = tmp_path / "bad.yaml"
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    cli_error(["compare", "--config", path, "--out", tmp_path / "o"], expected, tmp_path / "o")


@pytest.mark.cli
def test_a_missing_config_or_scenario_file(cli_error, tmp_path):
    cli_error(["compare", "--config", tmp_path / "none.yaml", "--out", tmp_path / "o"], "does not exist",
              tmp_path / "o")
    cli_error(["compare", "--config", tmp_path, "--out", tmp_path / "o"], "does not exist", tmp_path / "o")


@pytest.mark.cli
@pytest.mark.parametrize("content", [b"not a checkpoint", b"PK\x03\x04truncated zip", b"", bytes(range(256))])
def test_unreadable_checkpoints(cli_error, tmp_path, content):
    ckpt = tmp_path / "bad.ckpt"
    ckpt.write_bytes(content)
    cli_error(["evaluate", "--config", CONF / "tiny_evaluate.yaml", "--checkpoints", json.dumps({"x": str(ckpt)}),
               "--out", tmp_path / "o"], "not an eofnn predictor checkpoint", tmp_path / "o")


@pytest.mark.cli
@pytest.mark.slow
def test_output_paths_that_cannot_be_written(capsys, cli_error, tmp_path):
    a_file = tmp_path / "file.txt"
    a_file.write_text("mine")
    cli_error(["compare", "--config", TINY, "--out", a_file / "sub"], "is a file", a_file / "sub")
    cli_error(["compare", "--config", TINY, "--out", "/proc/eofnn_results"], "cannot be written",
              "/proc/eofnn_results")
    cli_error(["simulate", "--scenario", CONF / "tiny_scenario.yaml", "--out", tmp_path / "run.txt"],
              "suffix '.txt'", tmp_path / "run.txt")
    cli_error(["fit", "--scenario", CONF / "tiny_scenario.yaml", "--out", tmp_path], "is a folder",
              tmp_path / "never")
    code = main(["compare", "--config", str(TINY), "--out", str(a_file)])
    assert code == 2 and "is a file" in capsys.readouterr().err
    assert a_file.read_text() == "mine"


@pytest.mark.cli
@pytest.mark.parametrize("args, expected", [
    (["--predictor.checkpoint", "runs/cl.ckpt"], "does not run a checkpoint"),
    (["--predictor.controller", "predictor"], "simulate runs a baseline or a checkpoint"),
    (["--predictor.controller", "predictor", "--predictor.checkpoint", "/no/such.ckpt"], "does not exist"),
    (["--frames", "0"], "frames=0"),
    (["--realisations", "100000"], "realisations=100000"),
    (["--frames", "10000000", "--scenario.grid.n_across", "64"], "of memory"),
])
def test_simulate_never_runs_something_else(cli_error, tmp_path, args, expected):
    cli_error(["simulate", "--scenario", CONF / "tiny_scenario.yaml", *args, "--out", tmp_path / "run.fits"],
              expected, tmp_path / "run.fits")


@pytest.mark.cli
def test_a_psd_segment_longer_than_the_settled_frames(cli_error, tmp_path):
    cli_error(["compare", "--config", TINY, "--evaluation.psd_segment_frames", "4096", "--out", tmp_path / "o"],
              "psd_segment_frames=4096", tmp_path / "o")


@pytest.mark.cli
@pytest.mark.parametrize("drift, expected", [
    ("{start_s: 2, stop_s: 1, to: 2}", "plant.dm_gain_drift.stop_s=1.0 is invalid: it must be at least start_s"),
    ("{start_s: 0, stop_s: 1e9, to: 2}", "plant.dm_gain_drift.stop_s=1000000000.0 is invalid"),
    ("{start_s: 0, stop_s: 1, to_gain: 2}", "scenario.plant.dm_gain_drift: Option 'to_gain' is not accepted"),
])
def test_a_nested_optional_config_names_its_field_and_rule(tmp_path, cli_error, drift, expected):
    line = cli_error(["compare", "--config", TINY, "--scenario.plant.dm_gain_drift", drift,
                      "--out", tmp_path / "o"], expected, tmp_path / "o")
    assert "Union subtypes" not in line and "NoneType" not in line


def test_overwrite_keeps_the_files_eofnn_did_not_write(tmp_path, capsys):
    import warnings

    from eofnn.outputs import MANIFEST, staged_folder

    out = tmp_path / "results"
    with staged_folder(out) as folder:
        (folder / "metrics.json").write_text("old")
        (folder / "old_figure.png").write_text("old")
    (out / "notes.txt").write_text("mine")
    (out / "mine").mkdir()
    (out / "mine" / "data.csv").write_text("mine too")
    with warnings.catch_warnings(record=True) as caught, staged_folder(out, overwrite=True) as folder:
        warnings.simplefilter("always")
        (folder / "metrics.json").write_text("new")
    assert (out / "notes.txt").read_text() == "mine" and (out / "mine" / "data.csv").read_text() == "mine too"
    assert (out / "metrics.json").read_text() == "new" and not (out / "old_figure.png").exists()  # eofnn's: replaced
    assert "kept 2 file(s)" in str(caught[-1].message) and "notes.txt" in str(caught[-1].message)
    assert (out / MANIFEST).read_text().split() == ["metrics.json"]


def test_overwrite_of_a_folder_from_before_manifests_keeps_what_the_new_output_does_not_replace(tmp_path):
    from eofnn.outputs import staged_folder

    out = tmp_path / "results"
    out.mkdir()
    (out / "metrics.json").write_text("old")
    (out / "notes.txt").write_text("mine")
    with pytest.warns(UserWarning, match=r"kept 1 file\(s\) .*: notes.txt"), staged_folder(out, overwrite=True) as folder:
        (folder / "metrics.json").write_text("new")
    assert (out / "notes.txt").read_text() == "mine" and (out / "metrics.json").read_text() == "new"


@pytest.mark.cli
@pytest.mark.parametrize("override, expected", [
    (["--scenario.plant.dm_gain_drift", "{start_s: 100, stop_s: 101, to: 2}"],
     "plant.dm_gain_drift starts at 100 s (frame 100000), after the run of"),
    (["--scenario.atmosphere.changes", "[{at_s: 50, layer: 0, wind_speed_mps: 20}]"],
     "atmosphere.changes[0] starts at 50 s"),
    (["--scenario.vibrations", "[{mode: tip, frequency_hz: 40, amplitude_nm: 1e300}]"], "amplitude_nm=1e+300"),
    (["--scenario.plant.misregistration_x", "9.5", "--scenario.grid.n_across", "8"],
     "plant.misregistration_x=9.5 is invalid: it shifts the DM by more than the grid's 8 actuators across"),
])
def test_values_that_cannot_mean_what_they_say(tmp_path, cli_error, override, expected):
    cli_error(["compare", "--config", TINY, *override, "--out", tmp_path / "o"], expected, tmp_path / "o")


def test_a_neighbourhood_table_is_counted_before_it_is_built():
    from eofnn.errors import ConfigError
    from eofnn.sim.grid import ActuatorGrid

    assert ActuatorGrid(2.0, 10).neighbours(1.5).shape[1] == 9  # the count matches the table
    assert ActuatorGrid(2.0, 10).neighbours(2.0).shape[1] == 13
    with pytest.raises(ConfigError, match=r"a neighbourhood of radius 64 pitches \(12853 actuators each\) on \d+ "
                                          r"actuators needs about"):
        ActuatorGrid(8.0, 512).neighbours(64)


def test_positions_at_one_point_or_repeated_are_one_line():
    import numpy as np

    from eofnn.errors import TelemetryError
    from eofnn.sim.grid import ActuatorGrid

    with pytest.raises(TelemetryError, match="all lie at one point"):
        ActuatorGrid.from_positions(np.zeros((10, 2)))
    positions = np.array(ActuatorGrid(2.0, 10).positions_m)
    positions[1] = positions[0]
    with pytest.raises(TelemetryError, match="repeat"):
        ActuatorGrid.from_positions(positions)


def test_all_zero_telemetry_is_refused_before_a_fit(tmp_path):
    import torch

    from eofnn.data.history import HistorySpec
    from eofnn.errors import TelemetryError
    from eofnn.telemetry.record import Telemetry
    from eofnn.training.fit import FitOutput
    from eofnn.training.from_telemetry import fit_from_telemetry

    zeros = torch.zeros(500, 80, dtype=torch.float64)
    telemetry = Telemetry(y=zeros, wfs=zeros.clone(), delay_frames=2)
    with pytest.raises(TelemetryError, match="telemetry holds no signal"):
        fit_from_telemetry(telemetry, HistorySpec("open_loop", 3, 2), output=FitOutput(tmp_path / "z.ckpt"))
    assert not (tmp_path / "z.ckpt").exists()


@pytest.mark.cli
@pytest.mark.parametrize("args, whole", [
    (["compare", "--config", TINY, "--evaluation.frame", "2000"], "--evaluation.frames"),
    (["compare", "--config", TINY, "--evaluation.frame=2000"], "--evaluation.frames"),
    (["fit", "--scenario", CONF / "tiny_scenario.yaml", "--predictor.history_len", "3"], "--predictor.history_length"),
    (["simulate", "--scenario", CONF / "tiny_scenario.yaml", "--frame", "10"], "--frames"),
])
def test_an_abbreviated_option_is_refused_with_its_whole_name(cli_error, tmp_path, args, whole):
    """argparse would take ``--evaluation.frame 2000`` for ``--evaluation.frames 2000``: the option is refused,
    and the line names the option meant."""
    given = next(str(a).split("=")[0] for a in reversed(args) if str(a).startswith("--"))
    line = cli_error([*args, "--out", tmp_path / "o"], f"{given}: did you mean {whole}?", tmp_path / "o")
    assert "unrecognized arguments" in line


@pytest.mark.cli
@pytest.mark.parametrize("command", ["compare", "fit", "evaluate", "simulate", "stability", "sweep", "identify",
                                     "replay", "export"])
def test_no_subcommand_takes_an_abbreviation(cli_error, tmp_path, command):
    cli_error([command, "--ou", tmp_path / "o"], "--ou: did you mean --out?", tmp_path / "o")


@pytest.mark.cli
def test_the_whole_option_name_is_taken(tmp_path):
    from eofnn.cli.commands import parse

    parsed = parse(["compare", "--config", str(TINY), "--evaluation.frames", "2000", "--out", str(tmp_path / "o")])
    assert parsed.config.evaluation.frames == 2000
    assert not (tmp_path / "o").exists()  # parsed, not run


REALISTIC_SMALL = Path(__file__).parent.parent / "configs" / "realistic_small.yaml"


@pytest.mark.cli
def test_an_unset_psd_segment_follows_a_shortened_run(tmp_path):
    """``--evaluation.frames 1500`` with 500 settling frames leaves 1000 settled frames: the unset segment (1024 by
    default) becomes 512, the largest power of two they hold, and one line says so; at full length it stays 1024."""
    from eofnn.cli.commands import parse

    short = parse(["compare", "--config", str(REALISTIC_SMALL), "--evaluation.frames", "1500",
                   "--out", str(tmp_path / "o")]).config.evaluation
    assert short.psd_segment_frames is None and short.psd_segment_frames_used == 512
    assert short.psd_segment_note == ("evaluation.psd_segment_frames: 512 (the default 1024 is longer than the 1000 "
                                      "settled frames)")
    full = parse(["compare", "--config", str(REALISTIC_SMALL), "--out", str(tmp_path / "o")]).config.evaluation
    assert full.psd_segment_frames_used == 1024 and full.psd_segment_note is None  # no committed number moves
    assert not (tmp_path / "o").exists()


@pytest.mark.cli
def test_a_psd_segment_the_user_set_is_never_shortened(cli_error, tmp_path):
    line = cli_error(["compare", "--config", REALISTIC_SMALL, "--evaluation.frames", "1500",
                      "--evaluation.psd_segment_frames", "1024", "--out", tmp_path / "o"],
                     "evaluation.psd_segment_frames=1024 is invalid", tmp_path / "o")
    assert "[8, 1000]" in line


@pytest.mark.parametrize("frames, settle, used", [(5000, 500, 1024), (1524, 500, 1024), (1523, 500, 512),
                                                  (300, 50, 128), (108, 100, 8)])
def test_the_unset_psd_segment_is_the_largest_power_of_two_that_fits(frames, settle, used):
    from eofnn.evaluation.config import EvaluationConfig

    assert EvaluationConfig(frames=frames, settle_frames=settle).psd_segment_frames_used == used
    assert EvaluationConfig(frames=frames, settle_frames=settle, psd_segment_frames=8).psd_segment_frames_used == 8


def test_too_few_settled_frames_for_any_psd_segment():
    from eofnn.errors import ConfigError
    from eofnn.evaluation.config import EvaluationConfig

    with pytest.raises(ConfigError, match="leaves 7 settled frame"):
        EvaluationConfig(frames=107, settle_frames=100)


def test_the_experiment_says_when_the_psd_segment_was_shortened(small_scenario):
    from eofnn.evaluation.config import EvaluationConfig, PredictorConfig
    from eofnn.evaluation.experiment import Experiment

    lines: list[str] = []
    Experiment(small_scenario, {"nominal": {}}, {"integrator": PredictorConfig(controller="integrator", gain=0.4)},
               EvaluationConfig(frames=600, settle_frames=100), log=lines.append)
    assert lines == ["evaluation.psd_segment_frames: 256 (the default 1024 is longer than the 500 settled frames)"]
