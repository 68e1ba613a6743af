"""``data.plant_range``: each training sequence simulated in its own drawn plant, and what it buys an open-loop EOF.

Measured on the tiny scenario (4 taps, 3000 + 1000 frames, alpha 1e-6, no WFS noise): the nominal-trained EOF is
stable for DM gains in about (0.80, 1.14) and diverges at 1.25 (median residual 2.63 / 2.00 / diverged nm at
0.8 / 1.0 / 1.25); trained with the DM gain drawn in [0.8, 1.25] it is stable in about (0.76, 1.40), at 5.55 / 4.38 /
3.49 nm: robust over the range, at twice the nominal residual of the nominal filter.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from eofnn.analysis.linear import dm_gain_margin
from eofnn.data.config import DataConfig
from eofnn.data.history import HistorySpec
from eofnn.data.stream import LoopDataModule, sequence_plant
from eofnn.errors import ConfigError
from eofnn.sim.scenario import Scenario
from eofnn.training.fit import fit_predictor, recording_controller
from eofnn.training.task import OptimizationConfig

TINY = Path(__file__).parent / "conf" / "tiny_scenario.yaml"
RANGE = {"dm_gain": [0.8, 1.25]}
GAINS = (0.8, 1.0, 1.25)


def data(plant_range=None, **changes) -> DataConfig:
    return DataConfig(**{"frames": 3000, "val_frames": 1000, "sequence_frames": 1000, "seed": 3,
                         "plant_range": plant_range, **changes})


def measured(scenario: Scenario, plant_range):
    """The stable DM-gain interval of an open-loop EOF fitted with ``plant_range`` and its median residual (nm,
    ``None``: diverged) in closed loop at each of :data:`GAINS`."""
    fit = fit_predictor(scenario, "open_loop", 4, data=data(plant_range), optimization=OptimizationConfig(alpha=1e-6))
    interval = dm_gain_margin()(fit.network, fit.network.weight.detach(), fit.spec, 1.0, 1.0)
    rms = {g: scenario.median_residual_nm(fit.controller(), 1500, 7, "test", 200,
                                          plant=scenario.plant.with_errors(dm_gain=g)) for g in GAINS}
    return interval, rms


def test_a_range_trained_eof_is_stable_over_the_range_where_the_nominal_one_is_not():
    scenario = Scenario.from_yaml(TINY)
    (low, high), rms = measured(scenario, RANGE)
    assert low < 0.8 and high > 1.25
    assert all(rms[g] is not None for g in GAINS)
    assert max(rms.values()) <= 1.3 * rms[1.0]
    nominal_interval, nominal_rms = measured(scenario, None)
    assert nominal_interval is None or nominal_interval[1] < 1.25
    assert nominal_rms[1.25] is None
    assert nominal_rms[1.0] < rms[1.0]  # robustness is paid for at the nominal plant


def test_a_degenerate_range_is_the_nominal_fit_bit_for_bit():
    """[1, 1]: recorded in closed loop, the POL values are the turbulence exactly: the unranged stream's data."""
    scenario = Scenario.from_yaml(TINY)
    spec = HistorySpec.from_scenario("open_loop", 3, scenario)
    plain = LoopDataModule(scenario, spec, data()).dataset("train", 1000).sequence(0)
    ranged_data = data({"dm_gain": [1.0, 1.0]})
    ranged = LoopDataModule(scenario, spec, ranged_data, recording_controller(spec, ranged_data))
    x, t = ranged.dataset("train", 1000).sequence(0)
    torch.testing.assert_close(x, plain[0], rtol=0, atol=1e-9)
    assert torch.equal(t, plain[1])


def test_sequences_draw_different_plants_reproducibly():
    scenario = Scenario.from_yaml(TINY)
    ranged = data({"dm_gain": [0.8, 1.25], "misregistration_x": [-0.1, 0.1], "wfs_gain": [0.9, 1.1]})
    plants = [sequence_plant(scenario.plant, ranged, f"train:{i}") for i in range(5)]
    assert len({p.dm_gain for p in plants}) == 5 and len({p.misregistration_x for p in plants}) == 5
    assert all(0.8 <= p.dm_gain <= 1.25 and 0.9 <= p.wfs_gain <= 1.1 for p in plants)
    assert plants == [sequence_plant(scenario.plant, ranged, f"train:{i}") for i in range(5)]
    assert sequence_plant(scenario.plant, ranged, "validation:0") != plants[0]
    assert sequence_plant(scenario.plant, data({"dm_gain": [0.8, 1.25]}, seed=4), "train:0").dm_gain != plants[0].dm_gain
    assert sequence_plant(scenario.plant, data(), "train:0") is scenario.plant


def test_closed_loop_data_is_recorded_in_each_drawn_plant_reproducibly():
    scenario = Scenario.from_yaml(TINY)
    spec = HistorySpec.from_scenario("closed_loop", 2, scenario)
    ranged_data = data(RANGE)
    module = LoopDataModule(scenario, spec, ranged_data, recording_controller(spec, ranged_data))
    first, again = module.dataset("train", 2000), module.dataset("train", 2000)
    x0, t0 = first.sequence(0)
    x1, _ = first.sequence(1)
    assert torch.equal(x0, again.sequence(0)[0]) and torch.equal(t0, again.sequence(0)[1])
    assert not torch.equal(x0, x1)
    assert first.target_gain(0) == first.plant(0).dm_gain != first.target_gain(1)
    plain = LoopDataModule(scenario, spec, data(), recording_controller(spec, data())).dataset("train", 2000)
    assert plain.target_gain(0) == plain.target_gain(1) == scenario.plant.dm_gain


@pytest.mark.filterwarnings("ignore:network .* does not beat the trivial predictors")  # one short epoch
def test_a_network_trained_by_sgd_reads_the_same_ranged_stream(small_scenario):
    opt = OptimizationConfig(fit_method="sgd", epochs=1, lr=1e-3)
    fit = fit_predictor(small_scenario, "open_loop", 3, data=data(RANGE, frames=2000), optimization=opt)
    assert fit.val_loss is not None and torch.isfinite(torch.tensor(fit.val_loss))
    assert fit.info["data"]["plant_range"] == RANGE


@pytest.mark.parametrize(("plant_range", "message"), [
    ({"dm_gian": [0.8, 1.2]}, "data.plant_range has unknown field 'dm_gian': allowed are dm_gain, wfs_gain, "
                              "misregistration_x, misregistration_y"),
    ({"dm_gain": [1.25, 0.8]}, "data.plant_range.dm_gain=[1.25, 0.8] is invalid: low must be <= high"),
    ({"dm_gain": [0, 1.2]}, "data.plant_range.dm_gain=0 is invalid: it must be a finite number in (0, 100]"),
    ({"misregistration_y": [-12, 0]}, "data.plant_range.misregistration_y=-12 is invalid"),
    ({"dm_gain": 1.0}, "data.plant_range.dm_gain=1.0 is invalid: it must be [low, high]"),
    ([0.8, 1.2], "data.plant_range=[0.8, 1.2] is invalid: it must be a mapping of plant fields"),
])
def test_bad_ranges_are_refused_in_one_line(plant_range, message):
    with pytest.raises(ConfigError) as error:
        DataConfig(plant_range=plant_range)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_a_range_needs_simulator_truth_and_no_range_is_the_default():
    with pytest.raises(ConfigError, match="data.plant_range needs data.truth: true"):
        DataConfig(plant_range=RANGE, truth=False)
    assert DataConfig().plant_range is None and DataConfig(plant_range={}).plant_range is None
