"""The twin's reference turbulence on the range of the record's reconstructor (``eofnn.training.twin_seeing``):
a record whose reconstructor drops modes the twin's keeps (OOPAO's cut at 0.15 of the largest singular value beside
eofnn's 0.1) has a smaller structure function than the twin's at the same r0; the references are projected on the
modes the record's reconstructor outputs."""

from __future__ import annotations

import numpy as np

from eofnn.training.twin_seeing import fit_seeing, record_range, reference_covariances

CONFIG = {"grid": {"diameter_m": 3.2, "n_across": 8, "obstruction": 0.0},
          "atmosphere": {"r0_m": 0.1, "r0_wavelength_m": 5e-7, "outer_scale_m": 10.0, "model": "exact",
                         "layers": [{"wind_speed_mps": 10.0, "wind_direction_deg": 0.0}], "remove_ptt": True},
          "frame_rate_hz": 1000.0, "plant": {"delay_frames": 2},
          "sensor": {"kind": "shack_hartmann", "detector": {"band": "R", "magnitude": 8.0}}}
LAYERS = [{"weight": 1.0, "speed_mps": 10.0, "direction_deg": 0.0}]


def test_the_range_projector_matches_the_records_actuators_to_the_twins_and_is_none_where_nothing_is_dropped():
    rng = np.random.default_rng(0)
    k, s, rank = 12, 30, 8
    positions = rng.normal(size=(k, 2))
    q, _ = np.linalg.qr(rng.normal(size=(k, rank)))
    reconstructor = q @ rng.normal(size=(rank, s))
    order = rng.permutation(k)
    p = record_range(reconstructor, positions, positions[order])
    assert np.allclose(p, (q @ q.T)[np.ix_(order, order)], atol=1e-12)
    assert np.allclose(p @ p, p, atol=1e-12)
    assert record_range(None, positions, positions) is None
    assert record_range(rng.normal(size=(k, s)), positions, positions) is None  # every mode reconstructed
    assert record_range(reconstructor, positions, positions + 0.01) is None  # not the twin's actuators
    assert record_range(reconstructor, positions, positions[:-1]) is None


def test_a_record_whose_reconstructor_drops_modes_gets_its_r0_against_references_on_the_same_modes():
    """The record: the twin's own noise-free turbulence scaled to r0 0.15 m through a reconstructor that drops the
    10% of the actuator modes of highest spatial frequency (the grid Laplacian's), as a larger singular-value cut
    drops the modes a Shack-Hartmann sees worst: against the twin's full references its r0 comes out more than 5%
    high (the twin's aliased, noise-free reconstruction keeps much variance there); against the references on the
    record's range it is right. A reconstructor of full range leaves the references bit for bit."""
    frames, pitch = 1500, 3.2 / 8
    plain = reference_covariances(CONFIG, LAYERS, frames)
    where = plain[10.0][2]
    distance = np.linalg.norm(where[:, None] - where[None], axis=-1)
    neighbours = ((distance > 0) & (distance < 1.01 * pitch)).astype(float)
    _, modes = np.linalg.eigh(np.diag(neighbours.sum(1)) - neighbours)
    kept = modes[:, : int(0.9 * len(where))]
    rng = np.random.default_rng(1)
    reconstructor = kept @ rng.normal(size=(kept.shape[1], 2 * len(where)))
    projected = reference_covariances(CONFIG, LAYERS, frames, record=(reconstructor, where))
    p = kept @ kept.T
    for l0 in plain:
        for i in (0, 1):  # the covariance and the noise floor, both linear in the streams' products
            assert np.allclose(projected[l0][i], p @ plain[l0][i] @ p, rtol=0, atol=1e-9 * np.abs(plain[l0][i]).max())
    full = reference_covariances(CONFIG, LAYERS, frames, record=(rng.normal(size=(len(where), 2 * len(where))), where))
    assert all(np.array_equal(full[l0][i], plain[l0][i]) for l0 in plain for i in range(4))

    scale = (0.1 / 0.15) ** (5 / 3)  # r0 0.15 m: the same streams scaled, through the record's reconstructor
    for l0 in plain:
        truth = scale * p @ plain[l0][0] @ p
        right = fit_seeing(truth, {l0: projected[l0]}, where, pitch)["r0_m"]
        wrong = fit_seeing(truth, {l0: plain[l0]}, where, pitch)["r0_m"]
        assert abs(right / 0.15 - 1) < 1e-6, right
        assert wrong / 0.15 - 1 > 0.05, wrong


def test_eofnns_own_reconstructor_leaves_the_references_bit_for_bit():
    """eofnn's own Shack-Hartmann record: its reconstructor drops modes (the projector is not the identity) but the
    twin's streams already lie in its range, so the references are the same to the bit as without the record."""
    from eofnn.sim.loop.sensing import loop_operators
    from eofnn.sim.scenario import Scenario

    scenario = Scenario.from_dict(CONFIG)
    reconstructor = loop_operators(scenario.grid, scenario.sensor.shack_hartmann()).reconstructor.numpy()
    where = np.asarray(scenario.grid.positions_m)
    p = record_range(reconstructor, where, where)
    assert p is not None and round(float(np.trace(p))) < len(where)
    plain = reference_covariances(CONFIG, LAYERS, 1000)
    own = reference_covariances(CONFIG, LAYERS, 1000, record=(reconstructor, where))
    assert all(np.array_equal(own[l0][i], plain[l0][i]) for l0 in plain for i in range(4))
