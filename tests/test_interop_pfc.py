"""Predictive Fourier control on another simulator's actuators (eofnn/interop/pfc.py): a square lattice in any order
becomes eofnn's row-major grid, the controller runs in that order, and a layout with no lattice is refused."""

from __future__ import annotations

import numpy as np
import pytest

from eofnn.errors import ConfigError
from eofnn.interop.pfc import LatticeControl, LatticeGrid


def _lattice(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
    inside = (rows - 2.5) ** 2 + (cols - 2.5) ** 2 <= 9
    positions = np.stack([cols[inside], rows[inside]], 1) * 0.25 - 0.6  # (x, y) in metres, pitch 0.25
    order = np.random.default_rng(seed).permutation(len(positions))
    return positions[order], positions


def test_a_shuffled_lattice_is_read_in_row_major_order():
    shuffled, row_major = _lattice()
    grid = LatticeGrid(shuffled)
    assert np.allclose(grid.positions_m, row_major) and np.allclose(shuffled[grid.order], row_major)
    assert grid.n_across == 6 and grid.pitch_m == pytest.approx(0.25) and grid.n_actuators == len(shuffled)
    flat = grid.indices[:, 0] * grid.n_across + grid.indices[:, 1]
    assert np.all(np.diff(flat) > 0)  # what FourierBasis needs: the inside pixels row-major are the actuators
    basis = grid.ptt_basis()
    assert np.allclose(basis.T @ basis, np.eye(3))
    near = grid.neighbours(1.0).numpy()  # itself first, then its lattice neighbours (K beyond the edge)
    assert np.array_equal(near[:, 0], np.arange(grid.n_actuators))
    for i, row in enumerate(near):
        steps = np.abs(grid.indices[row[row < grid.n_actuators]] - grid.indices[i]).sum(1)
        assert sorted(steps)[0] == 0 and all(s == 1 for s in sorted(steps)[1:])


def test_the_controller_sees_the_lattice_order_and_commands_in_the_simulators():
    import torch

    shuffled, _ = _lattice(1)
    grid = LatticeGrid(shuffled)

    class Echo:  # commands what it read, so the permutation must round-trip
        def reset(self, batch, n, delay, dtype):
            self.seen = []

        def step(self, inp):
            self.seen.append(inp.wfs[0].clone())
            return inp.wfs * torch.arange(1, inp.wfs.shape[1] + 1, dtype=inp.wfs.dtype)

    control = LatticeControl(Echo(), 2, grid.order)
    control.reset(grid.n_actuators)
    measurement = np.arange(grid.n_actuators, dtype=np.float64) + 10
    command = control.step(measurement)
    assert np.allclose(control.controller.seen[0].numpy(), measurement[grid.order])
    expected = np.empty(grid.n_actuators)
    expected[grid.order] = measurement[grid.order] * np.arange(1, grid.n_actuators + 1)
    assert np.allclose(command, expected)


def test_actuators_off_any_square_lattice_are_refused_in_one_line():
    rng = np.random.default_rng(2)
    with pytest.raises(ConfigError, match="square lattice"):
        LatticeGrid(rng.uniform(-1, 1, (30, 2)))
