"""A predictor trained in eofnn's simulation carried into another simulator's loop (eofnn/interop/transfer.py): its
coefficients move by position, its commands through the loop's identified gain, and its wind is OOPAO's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.interop.transfer import EOFNN_DIRECTION_OF_OOPAO, eofnn_direction, transfer_filter
from eofnn.models.linear import LinearFilter
from eofnn.sim.grid import ActuatorGrid
from eofnn.training.export import filter_coefficients


def _network():
    grid = ActuatorGrid(2.0, 6)
    network = LinearFilter(grid.n_actuators, 2, "neighbourhood", 1.5,
                           {"diameter_m": 2.0, "n_across": 6, "obstruction": 0.0})
    with torch.no_grad():
        network.weight.copy_(torch.randn(network.weight.shape, generator=torch.Generator().manual_seed(1),
                                         dtype=torch.float64))
    return network, np.asarray(grid.positions_m)


def test_coefficients_move_by_position_and_the_extra_actuators_hold_their_pol_value():
    network, ours = _network()
    order = np.random.default_rng(2).permutation(len(ours))
    theirs = np.concatenate([ours[order], [[5.0, 5.0], [-5.0, 5.0]]])  # shuffled, plus two it lacks
    spec = HistorySpec("open_loop", 2, 2)
    runtime, moved = transfer_filter(network, spec, ours, theirs, dm_gain=2.0)
    assert moved == {"matched": len(ours), "held": 2}
    coefficients, neighbours = filter_coefficients(network)
    where = np.argsort(order)  # eofnn actuator e sits at index where[e] among theirs
    for e in range(len(ours)):
        assert np.allclose(runtime.coefficients[where[e]], coefficients[e] / 2.0)
        slots = runtime.neighbours[where[e]]  # the runtime reads index K (a zero) beyond the pupil
        assert np.array_equal(slots, np.where(neighbours[e] >= 0, where[np.clip(neighbours[e], 0, None)], len(theirs)))
    for held in (len(ours), len(ours) + 1):
        assert runtime.neighbours[held, 0] == held and runtime.coefficients[held, 0, 0] == -0.5
        assert np.count_nonzero(runtime.coefficients[held]) == 1


def test_actuators_off_the_other_layout_and_unmapped_winds_are_refused_in_one_line():
    network, ours = _network()
    with pytest.raises(ConfigError, match="not on the simulator's"):
        transfer_filter(network, HistorySpec("open_loop", 2, 2), ours, ours + 0.05, 2.0)
    with pytest.raises(ConfigError, match="not mapped"):
        eofnn_direction(30.0)


@pytest.mark.slow
def test_eofnns_mapped_wind_moves_the_turbulence_over_the_actuators_as_oopaos():
    """The turbulence ten frames on (one pitch at 20 m/s) matches the first frame shifted by one pitch along the
    same axis and sense in OOPAO (its DM's fit of the true phase) and in eofnn (its turbulence at the actuators)."""
    pytest.importorskip("OOPAO")
    from eofnn.interop.oopao import OopaoLoop
    from eofnn.interop.transfer import twin_scenario

    sim = OopaoLoop(8, 1.6, wind_speed_mps=20.0, wind_direction_deg=0.0)
    sim.reset(0)
    oopao = []
    for _ in range(11):
        sim.step_turbulence()
        oopao.append(sim.turbulence_fit_nm())
    scenario = twin_scenario(sim, 50)
    assert scenario.atmosphere.layers[0].wind_direction_deg == EOFNN_DIRECTION_OF_OOPAO[0.0]
    eofnn = scenario.turbulence(0, "direction", 1).frames(0, 11)[0].numpy()

    def best_shift(frames, positions) -> tuple[int, int]:
        key = {tuple(np.round(p / 0.2).astype(int)): i for i, p in enumerate(positions)}

        def corr(dx, dy):
            pairs = [(i, key[(k[0] + dx, k[1] + dy)]) for k, i in key.items() if (k[0] + dx, k[1] + dy) in key]
            i, j = np.array(pairs).T
            return np.corrcoef(frames[10][i], frames[0][j])[0, 1]

        return max(((1, 0), (-1, 0), (0, 1), (0, -1)), key=lambda d: corr(*d))

    assert best_shift(oopao, sim.positions_m) == best_shift(eofnn, np.asarray(scenario.grid.positions_m)) == (0, -1)


def test_static_gain_scales_the_carried_filter_to_cancel_a_constant_pol_value():
    network, ours = _network()
    runtime, _ = transfer_filter(network, HistorySpec("open_loop", 2, 2), ours, ours, 2.0, static_gain=True)
    assert np.median(runtime.coefficients.sum(axis=(1, 2))) == pytest.approx(-0.5)
    plain, _ = transfer_filter(network, HistorySpec("open_loop", 2, 2), ours, ours, 2.0)
    assert np.median(plain.coefficients.sum(axis=(1, 2))) != pytest.approx(-0.5)
    ratio = runtime.coefficients / plain.coefficients  # one scale for the whole filter: its shape is kept
    assert np.allclose(ratio, ratio.flat[0])
