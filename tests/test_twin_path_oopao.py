"""The whole twin path through OOPAO's adapter (``examples/twin_path.py``): OOPAO records, eofnn identifies its twin
from the files alone, trains in it, the guard decides on the record, the guarded filter is exported; and the grid
the twin builds for OOPAO's Fried DM, whose actuators reach past the lattice's inscribed circle."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "twin_path.py"
#: The tiny path: 8 x 8 subapertures on 1.6 m (pitch 0.2 m), 1500 frames, a 1000-frame fit in the twin.
TINY = ["--n-subap", "8", "--diameter", "1.6", "--frames", "1500", "--fit-frames", "1000", "--seed", "3"]
#: r0 is identified within this fraction of OOPAO's on the tiny record (docs/twin.md measures 4-14% on 20 x 20).
R0_BOUND = 0.3


def _example():
    spec = importlib.util.spec_from_file_location("twin_path", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    return example


def _fried(n_sub: int, pitch: float = 0.2, reach: float = 0.7533) -> np.ndarray:
    """OOPAO's Fried DM: a lattice of ``n_sub + 1`` across, the actuators within ``D / 2 + reach d``, row-major."""
    centres = (np.arange(n_sub + 1) - n_sub / 2) * pitch
    yy, xx = np.meshgrid(centres, centres, indexing="ij")
    pos = np.stack([xx.ravel(), yy.ravel()], axis=1)
    return pos[np.hypot(*pos.T) <= n_sub * pitch / 2 + reach * pitch]


def test_the_twin_grid_lists_oopaos_actuators_or_says_it_is_the_nearest():
    from eofnn.sim.grid import ActuatorGrid, nearest_grid

    for n_sub in (8, 10, 20):
        pos = _fried(n_sub)
        fields, exact = nearest_grid(pos, 0.2)
        grid = ActuatorGrid(**fields)
        assert exact and fields["n_across"] == n_sub + 1 and fields["active_diameter_m"] > fields["diameter_m"]
        assert grid.n_actuators == len(pos) and np.abs(grid.positions_m - pos).max() < 1e-9
    fields, exact = nearest_grid(np.delete(_fried(10), 7, axis=0), 0.2)  # one actuator missing: no such grid
    assert not exact and "active_diameter_m" not in fields and fields["n_across"] == 11


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """OOPAO's record at the tiny size and ``eofnn twin`` on its files; the example, its options, OOPAO's truth."""
    pytest.importorskip("OOPAO")
    example = _example()
    folder = tmp_path_factory.mktemp("oopao_twin")
    args = example.parse([*TINY, "--out", str(folder)])
    return example, args, folder, example.identify(args, folder)


@pytest.mark.slow
@pytest.mark.cli
def test_the_whole_path_through_oopao_from_its_telemetry_alone(recorded):
    """Recorded in OOPAO, nothing of its settings given to eofnn: the path completes, the guard's decision on the
    record is in replay.json with the checkpoint's sha256, the filter is exported exactly when the guard deployed it,
    and r0 is within :data:`R0_BOUND` of OOPAO's."""
    import hashlib

    import yaml

    from eofnn.sim.grid import ActuatorGrid

    example, args, folder, truth = recorded
    summary = {"truth_simulator_knowledge": truth, "identified": example.identified(folder),
               **example.train_and_guard(args, folder)}
    found = summary["identified"]
    guard = json.loads((folder / "guard" / "replay.json").read_text())["guard"]
    assert guard["deployed"] in ("predictor", "own_controller") and guard["why"]
    assert guard["checkpoint_sha256"] == hashlib.sha256((folder / "twin_eof.ckpt").read_bytes()).hexdigest()
    assert summary["guard"]["deployed"] == guard["deployed"]
    assert (folder / "filter.fits").exists() == (guard["deployed"] == "predictor") == bool(summary["exported"])
    assert abs(found["r0_m"][0] / truth["r0_m"] - 1) < R0_BOUND, (found, truth)
    twin = yaml.safe_load((folder / "twin" / "twin.yaml").read_text())
    assert ActuatorGrid(**twin["grid"]).n_actuators == truth["n_actuators"]  # OOPAO's very actuators
    assert example.report(summary).count("\n") >= 6

