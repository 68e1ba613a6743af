"""What a new user tripped over: a float32 module beside the config, warnings, telemetry size, plot names."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from eofnn.cli.main import main
from eofnn.sim import Telemetry

pytestmark = pytest.mark.cli

CONF = Path(__file__).parent / "conf"

MODULE = '''
import torch
class Plain(torch.nn.Module):
    """A float32 network (the torch default) that does not convert its input itself."""
    def __init__(self, n_taps):
        super().__init__()
        self.lin = torch.nn.Linear(n_taps, 1, bias=False)
        torch.nn.init.zeros_(self.lin.weight)
        with torch.no_grad():
            self.lin.weight[0, 0] = -1.0  # start as the pseudo-integrator: y(n) = -s_hat(n - d)
    def forward(self, history):
        return self.lin(history).squeeze(-1)
'''


@pytest.mark.slow
def test_a_float32_module_beside_the_config_trains_and_runs(tmp_path, capsys):
    (tmp_path / "mynet.py").write_text(MODULE)
    config = tmp_path / "mine.yaml"
    config.write_text(
        f"scenario: {CONF / 'tiny_scenario.yaml'}\n"
        "predictors:\n  mine:\n    history_length: 3\n    network: {class_path: mynet.Plain}\n"
        "    data: {frames: 600, val_frames: 200, sequence_frames: 600, batch_frames: 64}\n"
        "    optimization: {fit_method: sgd, lr: 0.01, epochs: 1}\n"
        "evaluation: {frames: 300, settle_frames: 50, psd_segment_frames: 64}\n")
    code = main(["compare", "--config", str(config), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 0, err
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())["scenarios"]["nominal"]["mine"]
    assert not m["diverged"] and m["median_rms_nm"] < 100


def test_a_config_without_layers_gives_no_serialisation_warning(tmp_path, capsys):
    config = tmp_path / "c.yaml"
    config.write_text("scenario: {grid: {n_across: 8, diameter_m: 2.0}, atmosphere: {r0_m: 0.1}}\n"
                      "predictors: {u: {controller: uncorrected}}\n")
    try:
        main(["compare", "--config", str(config), "--out", str(tmp_path / "o"), "--print_config"])
    except SystemExit as stop:
        assert stop.code == 0
    captured = capsys.readouterr()
    assert "Unable to serialize" not in captured.err and "wind_speed_mps: 5.1" in captured.out


@pytest.mark.slow
def test_float32_telemetry_is_half_the_size_and_fits_and_npz_keep_their_own_plots(tmp_path, capsys):
    sizes = {}
    for dtype in ("float64", "float32"):
        for suffix in (".fits", ".npz"):
            out = tmp_path / f"run_{dtype}{suffix}"
            code = main(["simulate", "--scenario", str(CONF / "tiny_scenario.yaml"), "--frames", "300",
                         "--predictor.controller", "integrator", "--dtype", dtype, "--out", str(out)])
            assert code == 0, capsys.readouterr().err
            assert out.with_name(out.name + ".png").exists()
            sizes[dtype, suffix] = out.stat().st_size
    for suffix in (".fits", ".npz"):
        assert sizes["float32", suffix] < 0.6 * sizes["float64", suffix]
    full, half = Telemetry.load(tmp_path / "run_float64.fits"), Telemetry.load(tmp_path / "run_float32.fits")
    assert (full.eps - half.eps).abs().max() < 1e-4 * full.eps.abs().max()
    summary = json.loads(capsys.readouterr().err.strip().splitlines()[-1])
    assert summary["settle_frames"] == 150  # statistics leave the start-up transient out


def test_a_config_copied_out_of_configs_finds_eofnns_own_scenario(tmp_path, capsys):
    root = Path(__file__).resolve().parent.parent
    copy = tmp_path / "mine.yaml"
    copy.write_text((root / "configs" / "realistic_small.yaml").read_text())  # names scenario: realistic.yaml
    try:
        main(["compare", "--config", str(copy), "--out", str(tmp_path / "o"), "--print_config"])
    except SystemExit as stop:
        assert stop.code == 0
    printed = capsys.readouterr().out
    assert "n_across: 40" in printed and "wind_speed_mps:" in printed  # realistic.yaml's scenario, loaded


def test_a_scenario_found_nowhere_lists_the_folders_searched_once(tmp_path, capsys):
    config = tmp_path / "mine.yaml"
    config.write_text("scenario: nowhere.yaml\n")
    assert main(["compare", "--config", str(config), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "scenario='nowhere.yaml'" in err and err.count("nowhere.yaml") == 1, err
    assert f"{tmp_path} (beside the config)" in err and "(eofnn's configs)" in err


def test_the_python_path_is_left_as_it_was(tmp_path):
    import sys

    config = tmp_path / "c.yaml"
    config.write_text("predictors: {u: {controller: uncorrected}}\n")
    before = list(sys.path)
    try:
        main(["compare", "--config", str(config), "--out", str(tmp_path / "o"), "--print_config"])
    except SystemExit:
        pass
    assert sys.path == before
