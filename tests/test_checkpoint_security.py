"""A checkpoint someone sent can never run code: networks are rebuilt only from an allowlist, checked before import."""

from __future__ import annotations

import json
import sys

import pytest
import torch

from eofnn.cli.main import main
from eofnn.data.stream import DataConfig
from eofnn.errors import CheckpointError
from eofnn.training.checkpoint import load_predictor
from eofnn.training.fit import FitOutput, fit_predictor
from eofnn.training.task import OptimizationConfig

MODULE = """
from pathlib import Path
Path({marker!r}).write_text("imported")   # what a malicious module would do: run code on import
import torch
class Net(torch.nn.Module):
    def __init__(self, n_actuators, n_taps):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(n_actuators, n_taps, dtype=torch.float64))
    def forward(self, history):
        return (history * self.weight).sum(-1)
"""


@pytest.fixture
def foreign_checkpoint(small_scenario, tmp_path, monkeypatch):
    """A real eofnn checkpoint whose network class_path is changed to an importable module that writes a marker."""
    marker = tmp_path / "marker.txt"
    (tmp_path / "planted_module.py").write_text(MODULE.format(marker=str(marker)))
    monkeypatch.syspath_prepend(str(tmp_path))
    path = tmp_path / "ol.ckpt"
    fit_predictor(small_scenario, "open_loop", 3, data=DataConfig(frames=400, val_frames=100, sequence_frames=400),
                  output=FitOutput(path))
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    ckpt["hyper_parameters"]["network"] = {"class_path": "planted_module.Net", "init_args": {}}
    forged = tmp_path / "forged.ckpt"
    torch.save(ckpt, forged)
    yield forged, marker
    sys.modules.pop("planted_module", None)


def test_a_checkpoint_naming_an_unknown_module_is_refused_before_import(foreign_checkpoint):
    forged, marker = foreign_checkpoint
    with pytest.raises(CheckpointError, match="planted_module.Net.*not one of eofnn's networks") as info:
        load_predictor(forged)
    assert "\n" not in str(info.value)
    assert not marker.exists() and "planted_module" not in sys.modules


@pytest.mark.cli
@pytest.mark.slow
def test_the_cli_refuses_it_too_and_trusting_it_by_name_lets_it_load(foreign_checkpoint, tmp_path, capsys):
    forged, marker = foreign_checkpoint
    args = ["evaluate", "--scenario", str(tmp_path / "scenario.yaml"), "--checkpoints", json.dumps({"x": str(forged)}),
            "--baselines", "[]", "--evaluation.frames", "300", "--evaluation.settle_frames", "50",
            "--evaluation.psd_segment_frames", "64"]
    (tmp_path / "scenario.yaml").write_text(
        "grid: {diameter_m: 2.0, n_across: 10}\natmosphere: {r0_m: 0.1, r0_wavelength_m: 5.0e-7, "
        "layers: [{wind_speed_mps: 10.0}]}\n")
    assert main([*args, "--out", str(tmp_path / "refused")]) == 2
    err = capsys.readouterr().err
    assert "not one of eofnn's networks" in err and len(err.strip().splitlines()) == 1
    assert not marker.exists() and not (tmp_path / "refused").exists()
    # Named by the user, the same class is trusted: now (and only now) its module is imported.
    code = main([*args, "--trusted_networks", "[planted_module.Net]", "--out", str(tmp_path / "trusted")])
    assert marker.exists()
    assert code == 0, capsys.readouterr().err


def test_eofnns_own_networks_need_no_trust(small_scenario, tmp_path):
    path = tmp_path / "mlp.ckpt"
    fit_predictor(small_scenario, "open_loop", 3, {"class_path": "MLP", "init_args": {"hidden": [4]}},
                  data=DataConfig(frames=300, val_frames=100, sequence_frames=300),
                  optimization=OptimizationConfig(fit_method="sgd"),
                  output=FitOutput(path))
    assert type(load_predictor(path).network).__name__ == "MLP"


def test_non_finite_weights_are_refused(small_scenario, tmp_path):
    path = tmp_path / "ol.ckpt"
    fit_predictor(small_scenario, "open_loop", 3, data=DataConfig(frames=400, val_frames=100, sequence_frames=400),
                  output=FitOutput(path))
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    ckpt["state_dict"]["network.weight"][0, 0] = float("nan")
    torch.save(ckpt, path)
    with pytest.raises(CheckpointError, match="non-finite weights"):
        load_predictor(path)
