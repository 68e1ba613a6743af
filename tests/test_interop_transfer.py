"""A predictor trained in eofnn's simulation carried into another simulator's loop (eofnn/studies/transfer.py): its
coefficients move by position, its commands through the loop's identified gain, and its wind is OOPAO's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.models.linear import LinearFilter
from eofnn.runtime import PredictiveFilter
from eofnn.sim.grid import ActuatorGrid
from eofnn.studies.transfer import (
    EOFNN_DIRECTION_OF_OOPAO,
    eofnn_direction,
    rim_actuators,
    splice_filters,
    transfer_filter,
)
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
        eofnn_direction(float("nan"))
    assert eofnn_direction(0.0) == 90.0 and eofnn_direction(30.0) == 60.0 and eofnn_direction(120.0) == 330.0


@pytest.mark.slow
def test_eofnns_mapped_wind_moves_the_turbulence_over_the_actuators_as_oopaos():
    """The turbulence ten frames on (one pitch at 20 m/s) matches the first frame shifted by one pitch along the
    same axis and sense in OOPAO (its DM's fit of the true phase) and in eofnn (its turbulence at the actuators)."""
    pytest.importorskip("OOPAO")
    from eofnn.interop.oopao import OopaoLoop
    from eofnn.studies.transfer import twin_scenario

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


def test_the_controlled_projector_keeps_the_loops_modes_on_eofnns_actuators_and_drops_the_rest():
    from types import SimpleNamespace

    from eofnn.studies.transfer import controlled_projector

    rng = np.random.default_rng(3)
    theirs = np.array([(x, y) for x in range(5) for y in range(5)], dtype=np.float64) * 0.2
    modes, _ = np.linalg.qr(rng.standard_normal((25, 8)))  # the loop's 8 seen modes, orthonormal
    sim = SimpleNamespace(positions_m=theirs, controlled_modes=modes)
    ours = theirs[::-1][:20]  # eofnn has 20 of the 25, in its own order
    p = controlled_projector(sim, ours).numpy()
    assert np.allclose(p, p.T) and np.allclose(p @ p, p)
    index = [24 - i for i in range(20)]
    restricted = modes[index]
    _, singular, vt = np.linalg.svd(restricted, full_matrices=False)
    kept = restricted @ vt[singular > 0.5].T  # the seen modes' directions on eofnn's actuators that survive
    assert np.allclose(p @ kept, kept)
    orthogonal = rng.standard_normal(20)
    orthogonal -= restricted @ np.linalg.lstsq(restricted, orthogonal, rcond=None)[0]
    assert np.allclose(p @ orthogonal, 0.0, atol=1e-10)


def test_the_carried_filters_noise_is_matched_and_reported_in_the_loops_command_units(monkeypatch):
    """OOPAO's commands are nm of influence-function peak, eofnn's nm of smooth surface (2.99 times more): the
    telemetry's noise is converted before eofnn's guide star is set, and the noise the filter was trained at is
    converted back before the loop compares it with its own."""
    from types import SimpleNamespace

    from eofnn.studies import transfer
    from eofnn.training import conditions

    seen = {}

    def train(sim, **kwargs):
        seen.update(kwargs)
        return SimpleNamespace(network=None, spec=None, info={"alpha": 1e-3}, val_loss=1.0), \
            SimpleNamespace(grid=SimpleNamespace(positions_m=None), sensor=SimpleNamespace(detector=None))

    monkeypatch.setattr(transfer, "train_in_eofnn", train)
    monkeypatch.setattr(transfer, "transfer_filter", lambda *a, **k: ("runtime", {"matched": 1, "held": 0}))
    monkeypatch.setattr(conditions, "scenario_conditions",
                        lambda scenario: conditions.Conditions(150.0, 1.0, (20.0,), "scenario"))
    sim = SimpleNamespace(surface_per_command=3.0, positions_m=None)
    plant = SimpleNamespace(wfs_noise_nm=40.0, dm_gain=1.8)
    runtime, info = transfer.eofnn_trained()(sim, plant)
    assert seen["noise_nm"] == pytest.approx(120.0) and seen["controlled"] is True
    assert info["conditions"]["wfs_noise_nm"] == pytest.approx(50.0) and info["conditions"]["dm_gain"] == 1.8
    assert seen["pupil"] == "grid" and info["twin_pupil"] == "grid"
    _, info = transfer.eofnn_trained(match_noise=False, controlled=False, pupil="oopao")(sim, plant)
    assert seen["noise_nm"] is None and seen["controlled"] is False
    assert seen["pupil"] == "oopao" and info["twin_pupil"] == "oopao"


@pytest.mark.slow
def test_oopaos_command_is_surface_per_command_nm_of_smooth_surface():
    pytest.importorskip("OOPAO")
    from eofnn.interop.oopao import OopaoLoop

    sim = OopaoLoop(8, 1.6)
    surface = np.asarray(sim.dm.modes) @ np.ones(sim.n_actuators)  # a uniform 1 nm command, per pupil pixel
    res = sim.pupil_mask.shape[0]
    centre = surface.reshape(res, res)[res // 2 - 2:res // 2 + 2, res // 2 - 2:res // 2 + 2]
    assert sim.surface_per_command == pytest.approx(2.99, abs=0.01)
    assert centre.mean() == pytest.approx(sim.surface_per_command, rel=0.02)


def test_a_spliced_filter_commands_each_actuator_as_the_filter_it_was_taken_from():
    network, ours = _network()
    spec = HistorySpec("open_loop", 2, 2)
    inner, _ = transfer_filter(network, spec, ours, ours, dm_gain=2.0)
    k, taps = inner.n_actuators, inner.taps
    rng = np.random.default_rng(3)
    outer = PredictiveFilter(rng.standard_normal((k, 1, len(taps))), taps, 2, 2.0, np.arange(k)[:, None])  # own only
    rim = rim_actuators(ours, 1.0)
    assert 0 < rim.sum() < k
    spliced = splice_filters(inner, outer, rim)
    for f in (inner, outer, spliced):
        f.reset()
    y_last = None
    for _ in range(8):
        wfs = rng.standard_normal(k)
        a, b, c = (f.step(wfs, y_last=y_last) for f in (inner, outer, spliced))
        assert np.allclose(c, np.where(rim, b, a))
        y_last = rng.standard_normal(k)  # the loop applies something else: all three read it
    assert np.abs(a - b).min() > 1e-6  # past the first frames the two filters command differently everywhere
    mismatched = PredictiveFilter(outer.coefficients, taps, 2, 1.0, np.arange(k)[:, None])
    with pytest.raises(ConfigError, match="same loop"):
        splice_filters(inner, mismatched, rim)
    with pytest.raises(ConfigError, match="one flag per actuator"):
        splice_filters(inner, outer, rim[:-1])


def test_the_rim_is_the_actuators_within_so_many_pitches_of_the_outermost():
    positions = np.asarray(ActuatorGrid(4.0, 20).positions_m)
    radius = np.hypot(*positions.T)
    for pitches in (1.0, 2.0):
        rim = rim_actuators(positions, pitches)
        assert np.array_equal(rim, radius > radius.max() - pitches * 0.2 - 1e-12)
    assert not rim_actuators(positions, 0.0).any()
    with pytest.raises(ConfigError, match="pitches"):
        rim_actuators(positions, -1.0)
    with pytest.raises(ConfigError, match="K >= 2"):
        rim_actuators(positions[:1], 1.0)
