"""alpha: auto — the ridge alpha chosen on validation data along a path, against a brute-force scan; the robustness
constraint against the stability analysis; bad values in one line."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from eofnn.analysis.linear import dm_gain_margin
from eofnn.analysis.stability import LoopSetup, analyse
from eofnn.data.history import HistorySpec
from eofnn.data.stream import DataConfig, LoopDataModule
from eofnn.errors import ConfigError
from eofnn.models.linear import LinearFilter
from eofnn.training.alpha import DEFAULT_ALPHA_PATH
from eofnn.training.fit import fit_predictor
from eofnn.training.ridge import NormalEquations
from eofnn.training.task import OptimizationConfig

DATA = DataConfig(frames=3000, val_frames=1000, sequence_frames=1000, seed=3)
PATH = [1e-12, 1e-10, 1e-8, 1e-6, 1e-4, 1e-2, 1.0]
TINY = Path(__file__).parent / "conf" / "tiny_compare.yaml"


def equations(scenario, spec, stream_frames, stream):
    """Normal equations of a per-actuator filter on one stream of the fit's own data."""
    module = LoopDataModule(scenario, spec, DATA)
    net = LinearFilter(scenario.grid.n_actuators, spec.n_taps)
    eq = NormalEquations()
    for x, t in module.dataset(stream, stream_frames):
        eq.update(net.features(x), net.group_targets(t))
    return eq


def test_the_default_path_spans_1e_14_to_1e_2():
    assert DEFAULT_ALPHA_PATH[0] == 1e-14 and DEFAULT_ALPHA_PATH[-1] == 1e-2 and len(DEFAULT_ALPHA_PATH) == 25
    assert OptimizationConfig().ridge_alpha == "auto"


@pytest.mark.slow
def test_auto_alpha_is_the_brute_force_minimum_of_the_validation_error(small_scenario):
    scenario = small_scenario.with_plant(wfs_noise_nm=2.0)
    spec = HistorySpec.from_scenario("open_loop", 4, scenario)
    result = fit_predictor(scenario, "open_loop", 4, data=DATA, optimization=OptimizationConfig(alpha_path=PATH))
    choice = result.predictor.info["alpha_choice"]
    train = equations(scenario, spec, DATA.frames, "train")
    val = equations(scenario, spec, DATA.val_frames, "validation")
    brute = [val.loss(train.solve(a).weights) for a in PATH]
    assert choice["path"]["alpha"] == PATH
    assert choice["path"]["val_loss"] == pytest.approx(brute, rel=1e-6)
    assert choice["unregularised_val_loss"] == pytest.approx(val.loss(train.solve(0.0).weights), rel=1e-6)
    best = PATH[min(range(len(PATH)), key=brute.__getitem__)]
    assert choice["alpha"] == best
    # With 2 nm of noise the optimum is interior: neither the smallest nor the largest alpha.
    assert PATH[0] < best < PATH[-1]
    direct = train.solve(best).weights
    assert torch.allclose(result.predictor.network.weight.detach(), direct, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("alpha, zero, says", [
    (1e-9, 5.0, ""),  # inside the path: nothing to say
    (1e-2, 5.0, "at an end of the path: extend alpha_path"),  # the upper end
    (1e-14, 10.0 * (1 + 2e-5), "differs by +2.0e-05 of it: a smaller alpha would barely matter"),
    (1e-14, 10.5, "differs by +5.00%: extend alpha_path below it"),
    (1e-14, None, "at an end of the path: extend alpha_path"),  # the unregularised fit is not finite
])
def test_an_alpha_at_the_lower_end_is_judged_by_the_unregularised_fit(alpha, zero, says):
    from eofnn.reporting.report import _alpha_edge

    path = [1e-14, 1e-9, 1e-2]
    choice = {"alpha": alpha, "val_loss": 10.0, "at_edge": alpha in (path[0], path[-1]), "path": {"alpha": path},
              "unregularised_val_loss": zero}
    text = _alpha_edge(choice)
    assert (says in text) if says else text == "", text


@pytest.mark.slow
def test_a_fixed_alpha_means_that_alpha(small_scenario):
    result = fit_predictor(small_scenario, "open_loop", 3, data=DATA, optimization=OptimizationConfig(alpha=1e-6))
    assert "alpha_choice" not in result.predictor.info
    assert result.rounds[-1]["alpha"] == 1e-6


@pytest.mark.slow
def test_select_keeps_the_best_alpha_that_meets_the_interval(small_scenario):
    spec = HistorySpec.from_scenario("open_loop", 4, small_scenario)
    interval = [0.7, 1.3]
    opt = OptimizationConfig(alpha_path=PATH, select={"dm_gain_interval": interval})
    result = fit_predictor(small_scenario, "open_loop", 4, data=DATA, optimization=opt, margin=dm_gain_margin())
    choice = result.predictor.info["alpha_choice"]
    low, high = choice["dm_gain_interval"]
    assert low <= interval[0] and high >= interval[1]
    weights = result.predictor.network.weight.detach()
    analysed = analyse(weights, "open_loop", 4, LoopSetup(2.0))
    assert analysed.gain_margin == pytest.approx((low, high), rel=1e-9)
    # Every alpha with a lower validation error breaks the interval (else it would have been chosen).
    train = equations(small_scenario, spec, DATA.frames, "train")
    losses = choice["path"]["val_loss"]
    for alpha, loss in zip(PATH, losses, strict=True):
        if loss < choice["val_loss"]:
            result_a = analyse(train.solve(alpha).weights, "open_loop", 4, LoopSetup(2.0))
            lo, hi = result_a.gain_margin
            assert not (result_a.stable and lo <= interval[0] and hi >= interval[1])


@pytest.mark.slow
def test_an_interval_no_alpha_meets_names_the_widest_reached(small_scenario):
    opt = OptimizationConfig(alpha_path=[1e-12, 1e-9], select={"dm_gain_interval": [0.01, 50.0]})
    with pytest.raises(ConfigError, match=r"cannot be met on the alpha path .*widest reached is \["):
        fit_predictor(small_scenario, "open_loop", 4, data=DATA, optimization=opt, margin=dm_gain_margin())


@pytest.mark.parametrize("options, expected", [
    ({"alpha": "auto", "fit_method": "sgd"}, "alpha='auto' is invalid with fit_method: sgd"),
    ({"alpha_path": []}, "alpha_path=[] is invalid: it must be a non-empty list"),
    ({"alpha_path": [1e-6, 1e-9]}, "it must be strictly increasing"),
    ({"alpha_path": [1e-9, math.nan]}, "non-empty list of finite alphas"),
    ({"select": {"dm_gain_interval": [1.1, 1.5]}}, "it must contain the nominal DM gain 1"),
    ({"select": {"dm_gain_interval": [1.2, 0.8]}}, "two increasing finite DM gains"),
    ({"select": {"margin": 3}}, "the only constraint is {dm_gain_interval"),
    ({"alpha": 1e-6, "select": {"dm_gain_interval": [0.8, 1.2]}}, "select needs alpha: auto"),
    ({"alpha": "often"}, "alpha='often' is invalid"),
])
def test_bad_tuning_options_are_one_line(options, expected):
    with pytest.raises(ConfigError) as err:
        OptimizationConfig(**options)
    assert expected in str(err.value) and "\n" not in str(err.value)


@pytest.mark.cli
def test_bad_tuning_options_on_the_command_line(cli_error, tmp_path):
    out = tmp_path / "out"
    cli_error(["compare", "--config", TINY, "--out", out, "--predictors.ol_eof.optimization.alpha_path", "[1e-3, 1e-6]"],
              "strictly increasing", out)


@pytest.mark.slow
def test_a_budgeted_search_keeps_the_best_trial_and_reports_its_budget(small_scenario):
    """SGD's twin of alpha: auto: learning rate x width with early stopping, chosen on validation data."""
    from eofnn.training.search import check_search

    scenario = small_scenario.with_plant(wfs_noise_nm=1.0)
    search = {"lr": [1e-4, 3e-3], "width": [4, 16], "patience": 1}
    opt = OptimizationConfig(fit_method="sgd", epochs=2, search=search)
    data = DataConfig(frames=400, val_frames=200, sequence_frames=400, batch_frames=100, seed=2)
    network = {"class_path": "eofnn.models.mlp.MLP", "init_args": {"hidden": [8, 8]}}
    result = fit_predictor(scenario, "open_loop", 3, network, data=data, optimization=opt)
    searched = result.predictor.info["search"]
    assert len(searched["trials"]) == 4
    losses = [t["val_loss"] for t in searched["trials"]]
    assert searched["chosen"]["val_loss"] == min(losses)
    assert result.predictor.network_config["init_args"]["hidden"] == [searched["chosen"]["width"]] * 2
    budget = searched["budget"]
    assert budget["epochs"] == sum(t["epochs"] for t in searched["trials"]) and budget["frames"] == 400 * budget["epochs"]
    assert all(1 <= t["best_epoch"] <= t["epochs"] <= 2 for t in searched["trials"])
    # The chosen network is the one restored at its best epoch: its validation loss is the one reported.
    module = LoopDataModule(scenario, HistorySpec.from_scenario("open_loop", 3, scenario), data)
    with torch.no_grad():
        sq = [(result.predictor.network(x.float()).double() - t).pow(2).mean().item() * len(x)
              for x, t in module.val_dataloader()]
    n = sum(len(x) for x, _ in module.val_dataloader())
    assert sum(sq) / n == pytest.approx(searched["chosen"]["val_loss"], rel=1e-3)
    with pytest.raises(ConfigError, match="search.lr"):
        check_search({"lr": []}, 1e-3)
    with pytest.raises(ConfigError, match="is for fit_method: sgd"):
        OptimizationConfig(search={"lr": [1e-3]})
