"""Any actuator layout: KD-tree neighbourhoods, identification, fits and checkpoints on Fried, hexagonal and
jittered layouts (telemetry from tests/layout_telemetry.py: a known plant, frozen flow of Fourier modes)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from layout_telemetry import fried_positions, hex_positions, jittered_positions, record

from eofnn.cli.main import main
from eofnn.data.history import HistorySpec
from eofnn.errors import TelemetryError
from eofnn.evaluation.replay import replay
from eofnn.models.linear import LinearFilter
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.layout import ActuatorLayout, apply_shift, layout_from_dict, layout_from_positions
from eofnn.telemetry.record import Telemetry
from eofnn.training.checkpoint import load_predictor
from eofnn.training.fit import FitOutput
from eofnn.training.from_telemetry import fit_from_telemetry
from eofnn.training.identify import identify_plant

LAYOUTS = {"fried": fried_positions, "hexagonal": hex_positions, "jittered": jittered_positions}
NEIGHBOURHOOD = {"class_path": "eofnn.models.linear.LinearFilter",
                 "init_args": {"structure": "neighbourhood", "radius": 1.5}}


@pytest.mark.parametrize("obstruction", [0.0, 0.3])
def test_kdtree_neighbours_equal_the_grid_index_ones_on_eofnns_grid(obstruction):
    grid = ActuatorGrid(8.0, 10, obstruction)
    layout = ActuatorLayout(grid.positions_m)
    assert layout.pitch_m == pytest.approx(grid.pitch_m) and layout.kind == "square"
    for radius in (0.5, 1.0, 1.5, 2.0, 2.9):
        assert torch.equal(layout.neighbours(radius), grid.neighbours(radius)), radius
    # Networks built from positions read the same neighbourhoods as from the grid's fields.
    by_grid = LinearFilter(grid.n_actuators, 3, "neighbourhood", 1.5, {"diameter_m": 8.0, "n_across": 10,
                                                                         "obstruction": obstruction})
    by_positions = LinearFilter(grid.n_actuators, 3, "neighbourhood", 1.5, layout.to_dict())
    assert torch.equal(by_grid.neighbours, by_positions.neighbours)
    # eofnn's own grid in telemetry positions stays eofnn's grid (same tables, same numbers as before).
    recovered = layout_from_positions(grid.positions_m)
    assert isinstance(recovered, ActuatorGrid) and np.allclose(recovered.positions_m, grid.positions_m)


def test_layout_tables():
    fried, hexagonal, jittered = (ActuatorLayout(f()) for f in LAYOUTS.values())
    assert fried.kind == "square" and fried.is_regular(1.5) and fried.neighbours(1.5).shape[1] == 9
    # Hexagonal: the 6 nearest at one pitch, one column per offset for every actuator.
    assert hexagonal.kind == "triangulated" and hexagonal.is_regular(1.5)
    assert hexagonal.neighbours(1.5).shape[1] == 7
    offsets = hexagonal.neighbour_offsets(1.5)
    full = ~np.isnan(offsets).any((1, 2))
    assert np.allclose(np.hypot(*offsets[full][:, 1:].T), 1.0) and np.allclose(offsets[full], offsets[full][0])
    # Jittered: rows by distance, padded with K; every listed neighbour is within the radius.
    table = jittered.neighbours(2.0).numpy()
    assert not jittered.is_regular(2.0) and (table[:, 0] == np.arange(jittered.n_actuators)).all()
    distance = np.where(table < jittered.n_actuators, np.hypot(*np.nan_to_num(jittered.neighbour_offsets(2.0)).T).T, 0)
    assert distance.max() <= 2.0 + 1e-9 and (np.diff(np.where(table < jittered.n_actuators, distance, 9), 1) >= 0).all()


@pytest.mark.slow
@pytest.mark.parametrize("name", list(LAYOUTS))
def test_identify_gain_2_and_misregistration_on_layouts(name):
    tel = record(LAYOUTS[name](), 3000, misregistration=(0.2, -0.1), noise_nm=2.0)
    plant = identify_plant(tel, radius=2.0 if name == "jittered" else 1.5)
    assert plant.identified and plant.lag_frames == 0 and not plant.warnings
    assert abs(plant.dm_gain / 2 - 1) < 0.02
    assert abs(plant.misregistration_x - 0.2) < 0.02 and abs(plant.misregistration_y + 0.1) < 0.02
    assert plant.wfs_noise_nm == pytest.approx(2.0, rel=0.2)
    # plant.json holds the layout; the model it rebuilds applies what the loop applied.
    assert plant.grid == {"positions_m": LAYOUTS[name]().tolist()}
    y = torch.randn(5, len(plant.grid["positions_m"]), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    truth = 2 * apply_shift(y, layout_from_dict(plant.grid).shift_operator(0.2, -0.1))
    assert torch.allclose(plant.dm_response()(y), truth, atol=0.05)


def test_too_few_actuators_for_a_shift_model_and_no_positions():
    xx, yy = np.meshgrid(np.arange(6) * 0.2, np.arange(2) * 0.2)
    small = np.stack([xx.ravel(), yy.ravel()], 1)  # two rows of a square lattice: no actuator has its 3 x 3 block
    plant = identify_plant(record(small, 2000, dm_gain=2.0))
    assert abs(plant.dm_gain / 2 - 1) < 0.02 and plant.misregistration_x is None
    assert len(plant.warnings) == 1 and "no actuator has the stencil of the shift model" in plant.warnings[0]
    bare = identify_plant(record(hex_positions(), 2000, with_positions=False))
    assert abs(bare.dm_gain / 2 - 1) < 0.02 and "no actuator positions" in bare.warnings[0]


@pytest.mark.slow
def test_fit_on_fried_with_neighbourhoods_beats_the_integrator_and_checkpoints_reload(tmp_path):
    pos = fried_positions()
    train, held_out = record(pos, 3000, seed=0, noise_nm=1.0), record(pos, 1500, seed=5, noise_nm=1.0)
    plant = identify_plant(train)
    spec = HistorySpec("open_loop", 4, 2)
    fit = fit_from_telemetry(train, spec, NEIGHBOURHOOD, plant=plant, output=FitOutput(tmp_path / "fried.ckpt"))
    result = replay(fit.network, spec, held_out, plant=plant, start=100)
    per_actuator = replay(fit_from_telemetry(train, spec, plant=plant).network, spec, held_out, plant=plant, start=100)
    assert result.predictor.median_rms_nm < 0.1 * result.own_controller.median_rms_nm
    assert result.predictor.median_rms_nm < per_actuator.predictor.median_rms_nm  # neighbours help
    loaded = load_predictor(tmp_path / "fried.ckpt")
    assert torch.equal(loaded.network.neighbours, ActuatorLayout(pos).neighbours(1.5))
    assert torch.equal(loaded.network.weight, fit.network.weight)


@pytest.mark.slow
@pytest.mark.cli
def test_identify_from_the_command_line_on_a_hexagonal_file(tmp_path, capsys):
    tel = record(hex_positions(), 2500)
    np.savez(tmp_path / "hex.npz", y=tel.y.numpy(), wfs=tel.wfs.numpy(), positions_m=hex_positions(), delay_frames=2)
    assert main(["identify", "--telemetry", str(tmp_path / "hex.npz"), "--out", str(tmp_path / "plant.json")]) == 0
    plant = json.loads((tmp_path / "plant.json").read_text())
    assert abs(plant["dm_gain"] / 2 - 1) < 0.02 and abs(plant["misregistration_x"]) < 0.01


@pytest.mark.cli
def test_bad_positions_and_sparse_layouts(tmp_path, cli_error):
    tel = record(hex_positions(), 600)
    y, wfs, pos = tel.y.numpy(), tel.wfs.numpy(), hex_positions()
    duplicate, nan = pos.copy(), pos.copy()
    duplicate[5] = duplicate[4]
    nan[3, 1] = np.nan
    cases = {"duplicates": (duplicate, "duplicates: rows 4 and 5"), "nan": (nan, "positions_m' holds 1 non-finite"),
             "count": (pos[:-1], "positions_m has shape (90, 2): expected (91, 2)")}
    for name, (bad, message) in cases.items():
        path = tmp_path / f"{name}.npz"
        np.savez(path, y=y, wfs=wfs, positions_m=bad, delay_frames=2)
        assert message in cli_error(["identify", "--telemetry", path, "--out", tmp_path / f"{name}.json"], alone=False)
        assert not (tmp_path / f"{name}.json").exists()
    # A sparse layout: one actuator far from the others has no neighbour within the radius.
    sparse = np.concatenate([fried_positions(4), [[3.0, 3.0]]])
    with pytest.raises(TelemetryError, match=r"too sparse for neighbourhood radius 1.5 pitches .* allowed: radius >="):
        ActuatorLayout(sparse).neighbours(1.5)
    with pytest.raises(TelemetryError, match="duplicates"):
        Telemetry(y=y, wfs=wfs, delay_frames=2, positions_m=duplicate)
    path = tmp_path / "sparse.npz"
    k = len(sparse)
    np.savez(path, y=np.random.default_rng(0).standard_normal((600, k)), wfs=np.zeros((600, k)), positions_m=sparse,
             delay_frames=2)
    line = cli_error(["fit", "--telemetry", path, "--plant", "nominal", "--predictor.network",
                      json.dumps(NEIGHBOURHOOD), "--out", tmp_path / "sparse.ckpt"], alone=False)
    assert "too sparse" in line and not (tmp_path / "sparse.ckpt").exists()


@pytest.mark.slow
def test_lag_is_found_on_a_layout_and_without_positions():
    """A file whose wfs is logged one frame late: the lag (and then the gain) needs no geometry."""
    pos = hex_positions()
    tel = record(pos, 3000, noise_nm=1.0)
    for positions in (pos, None):
        late = identify_plant(Telemetry(y=tel.y[1:], wfs=tel.wfs[:-1], delay_frames=2, positions_m=positions))
        assert late.lag_frames == 1 and abs(late.dm_gain / 2 - 1) < 0.02 and "1 frame(s) behind" in late.warnings[0]
