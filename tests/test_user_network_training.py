"""A user's own nn.Module trained by gradient descent: scaled so that it learns, compared with the trivial
predictors, and one line naming it when it misbehaves (wrong shape, raising, no parameters, NaN)."""

from __future__ import annotations

import pytest

from eofnn.data.stream import DataConfig
from eofnn.errors import ConfigError
from eofnn.training.fit import FitOutput, fit_predictor
from eofnn.training.task import OptimizationConfig

MODULE = '''
import torch
from torch import nn

class Plain(nn.Module):
    """torch's default initialisation, no scaling of its own: what a new user writes first."""
    def __init__(self, n_taps):
        super().__init__()
        self.lin = nn.Linear(n_taps, 1)
    def forward(self, history):
        return self.lin(history).squeeze(-1)

class WrongShape(nn.Module):
    def __init__(self, n_taps):
        super().__init__()
        self.lin = nn.Linear(n_taps, 2)
    def forward(self, history):
        return self.lin(history)

class Raises(nn.Module):
    def __init__(self):
        super().__init__()
        self.w = nn.Parameter(torch.zeros(1))
    def forward(self, history):
        raise RuntimeError("my bug")

class NoParameters(nn.Module):
    def forward(self, history):
        return -history[..., 0]

class MakesNaN(nn.Module):
    def __init__(self, n_taps):
        super().__init__()
        self.lin = nn.Linear(n_taps, 1)
    def forward(self, history):
        return self.lin(history).squeeze(-1) * float("nan")
'''

DATA = DataConfig(frames=1500, val_frames=500, sequence_frames=1500, batch_frames=64)


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    (tmp_path / "my_nets.py").write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def fit(scenario, name, tmp_path=None, **optimization):
    options = {"fit_method": "sgd", "lr": 0.02, "epochs": 3, **optimization}
    return fit_predictor(scenario, "open_loop", 3, {"class_path": f"my_nets.{name}"}, data=DATA,
                         optimization=OptimizationConfig(**options),
                         output=FitOutput(None if tmp_path is None else tmp_path / "net.ckpt"))


@pytest.mark.slow
def test_plain_sgd_diverges_on_nanometres_and_learns_when_normalised(small_scenario, user_module, tmp_path):
    # Histories of ~300 nm make the squared-error gradient ~1e5 times too large for plain SGD: it blows up.
    with pytest.raises(ConfigError, match=r"network my_nets.Plain gave a training loss of (nan|inf) \(not finite\)"):
        fit(small_scenario, "Plain", tmp_path, optimizer="sgd", lr=0.1, normalize=False)
    assert not (tmp_path / "net.ckpt").exists()
    with pytest.warns(UserWarning, match="does not beat the trivial predictors"):  # learns, slowly: said in one line
        scaled = fit(small_scenario, "Plain", tmp_path, optimizer="sgd", lr=0.1)  # normalize: on by default
    zero_command = 9.0e4  # nm^2: the turbulence's variance on the validation data
    assert scaled.val_loss < zero_command / 10 and (tmp_path / "net.ckpt").is_file()


def test_the_warning_names_the_network_and_the_cure(small_scenario, user_module):
    with pytest.warns(UserWarning, match=r"network my_nets.Plain does not beat the trivial predictors on validation "
                                         r"data \(loss .* nm\^2; zero command .*, pseudo-integrator .* nm\^2\).*"
                                         r"try optimization.normalize: true"):
        fit(small_scenario, "Plain", normalize=False, epochs=1)


def test_trivial_losses_are_the_zero_command_and_the_scaled_last_value():
    import torch

    from eofnn.training.task import trivial_losses

    history = torch.randn(4, 5, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    target = -2.0 * history[..., 0]
    losses = trivial_losses([(history, target)], "open_loop")
    assert losses["zero command"] == pytest.approx(float(target.pow(2).mean()))
    assert losses["pseudo-integrator"] == pytest.approx(0.0, abs=1e-12)
    assert set(trivial_losses([(history, target)], "closed_loop")) == {"zero command"}


@pytest.mark.slow
@pytest.mark.parametrize("name, message", [
    ("WrongShape", "network my_nets.WrongShape returned shape (2, 80, 2) for a history of shape (2, 80, 3)"),
    ("Raises", "network my_nets.Raises: forward raised RuntimeError: my bug"),
    ("NoParameters", "network my_nets.NoParameters has no trainable parameters"),
    ("MakesNaN", "network my_nets.MakesNaN gave a training loss of nan (not finite): nothing was saved"),
])
def test_a_misbehaving_network_is_one_line_and_saves_nothing(small_scenario, user_module, tmp_path, name, message):
    with pytest.raises(ConfigError) as info:
        fit(small_scenario, name, tmp_path)
    assert message in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / "net.ckpt").exists()
