"""The numpy-only runtime runs an exported filter exactly as eofnn's PredictiveController does."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from astropy.io import fits

from eofnn.control.predictive import PredictiveController
from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError, OutputExistsError
from eofnn.models.linear import LinearFilter
from eofnn.runtime import FilterFileError, PredictiveFilter
from eofnn.sim import LoopInput, run_loop
from eofnn.training.export import export_filter, filter_taps

ROOT = Path(__file__).resolve().parent.parent


def random_filter(grid, spec: HistorySpec, structure: str, seed: int = 0) -> LinearFilter:
    net = LinearFilter(grid.n_actuators, spec.n_taps, structure, 1.5, {"diameter_m": grid.diameter_m,
                                                                      "n_across": grid.n_across, "obstruction": 0.0})
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():  # small enough that the commands stay of the size of the inputs
        net.weight.copy_(0.1 * torch.randn(net.weight.shape, generator=gen, dtype=torch.float64) / net.weight.shape[1])
    return net


class RuntimeController:
    """The runtime behind eofnn's loop-controller protocol (batch of one), to close an eofnn loop with it."""

    def __init__(self, runtime: PredictiveFilter) -> None:
        self.runtime = runtime

    def reset(self, batch, n_actuators, delay_frames, dtype) -> None:
        assert batch == 1 and delay_frames == self.runtime.delay_frames
        self.runtime.reset()

    def step(self, inp: LoopInput) -> torch.Tensor:
        return torch.from_numpy(self.runtime.step(inp.wfs[0].numpy()))[None]


@pytest.mark.slow
@pytest.mark.parametrize("kind,structure,gain", [("closed_loop", "per_actuator", 1.0), ("open_loop", "per_actuator", 2.0),
                                                 ("closed_loop", "neighbourhood", 1.0), ("open_loop", "shared", 1.5)])
def test_runtime_matches_predictive_controller(small_scenario, tmp_path, kind, structure, gain):
    spec = HistorySpec(kind, 3, 2)
    net = random_filter(small_scenario.grid, spec, structure)
    path = export_filter(net, spec, tmp_path / "filter.fits", dm_gain_model=gain,
                         positions_m=small_scenario.grid.positions_m)
    runtime = PredictiveFilter.from_file(path)
    controller = PredictiveController(net, spec, gain)
    k = small_scenario.grid.n_actuators
    controller.reset(1, k, 2, torch.float64)
    gen = torch.Generator().manual_seed(1)
    for n in range(60):  # the same measurement stream into both
        wfs = 50 * torch.randn(1, k, generator=gen, dtype=torch.float64)
        expected = controller.step(LoopInput(n, wfs, torch.zeros_like(wfs)))[0].numpy()
        got = runtime.step(wfs[0].numpy())
        assert np.abs(got - expected).max() < 1e-9
        assert (n < spec.first_frame) == (not got.any())
    # Closing an eofnn loop with the runtime gives the loop of the PredictiveController, to 1e-9 nm.
    turbulence = small_scenario.turbulence(0)
    by_runtime = run_loop(turbulence, small_scenario.plant, RuntimeController(runtime), 200).telemetry.y
    by_eofnn = run_loop(small_scenario.turbulence(0), small_scenario.plant, controller, 200).telemetry.y
    assert (by_runtime - by_eofnn).abs().max() < 1e-9


def test_file_layout_and_y_last(small_scenario, tmp_path):
    spec = HistorySpec("closed_loop", 2, 2)
    net = random_filter(small_scenario.grid, spec, "neighbourhood")
    path = export_filter(net, spec, tmp_path / "f.fits")
    with fits.open(path) as hdul:
        header = hdul[0].header
        assert (header["HISTKIND"], header["HISTLEN"], header["DELAY"], header["NTAPS"]) == ("closed_loop", 2, 2, 4)
        assert hdul[0].data.shape == (small_scenario.grid.n_actuators, 9, 4)
        assert [(s, int(lag)) for s, lag in zip(hdul["TAPS"].data["SIGNAL"], hdul["TAPS"].data["LAG"], strict=True)] \
            == filter_taps(spec) == [("y", 1), ("y", 2), ("wfs", 2), ("wfs", 3)]
        assert (hdul["NEIGHBOURS"].data == -1).any()  # rim actuators have slots beyond the pupil
    runtime = PredictiveFilter.from_file(path)
    k = small_scenario.grid.n_actuators
    ones = np.ones(k)
    outputs = [runtime.step(ones) for _ in range(5)]
    again = [runtime.step(ones, y_last=outputs[-1] if i == 0 else None) for i in range(1)]
    runtime.reset()
    replayed = [runtime.step(ones) for _ in range(6)]
    np.testing.assert_allclose(replayed[-1], again[0])  # y_last equal to its own output changes nothing
    runtime.reset()
    [runtime.step(ones) for _ in range(5)]
    assert np.abs(runtime.step(ones, y_last=outputs[-1] + 100.0) - again[0]).max() > 1e-6


@pytest.mark.cli
def test_runtime_imports_numpy_and_astropy_only():
    tree = ast.parse((ROOT / "eofnn" / "runtime.py").read_text())
    modules = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    modules |= {node.module.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    assert modules <= {"__future__", "pathlib", "numpy", "astropy"}
    # And it runs as a lone file, copied away from the package.
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import runtime; "
            "f = runtime.PredictiveFilter([[0.5, 0.25]], [('wfs', 2), ('wfs', 3)], 2); "
            "print([float(f.step([1.0])[0]) for _ in range(4)])")
    out = subprocess.run([sys.executable, "-c", code, str(ROOT / "eofnn")], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[0.0, 0.0, 0.0, 0.75]"


def test_bad_filters(small_scenario, tmp_path):
    spec = HistorySpec("open_loop", 2, 2)
    net = random_filter(small_scenario.grid, spec, "per_actuator")
    with pytest.raises(ConfigError, match="taps"):
        export_filter(net, HistorySpec("open_loop", 3, 2), tmp_path / "x.fits")
    path = export_filter(net, spec, tmp_path / "x.fits")
    with pytest.raises(OutputExistsError):
        export_filter(net, spec, path)
    with pytest.raises(FilterFileError, match="does not exist"):
        PredictiveFilter.from_file(tmp_path / "none.fits")
    (tmp_path / "junk.fits").write_bytes(b"junk" * 1000)
    with pytest.raises(FilterFileError, match="not readable"):
        PredictiveFilter.from_file(tmp_path / "junk.fits")
    with pytest.raises(FilterFileError, match="not available"):
        PredictiveFilter([[1.0]], [("wfs", 1)], 2)
    runtime = PredictiveFilter.from_file(path)
    with pytest.raises(ValueError, match="shape"):
        runtime.step(np.zeros(3))


@pytest.mark.parametrize("args, message", [
    (([[1.0]], [("pol", 10**9)], 2), "lag 1000000000) is invalid: lags are at most 10000"),
    (([[np.nan, np.nan]], [("pol", 2), ("pol", 3)], 2), "2 non-finite value(s)"),
    (([[1.0]], [("pol", 2)], 2, -1.0), "dm_gain_model=-1.0 is invalid"),
    ((np.ones((2, 2, 1)), [("pol", 2)], 2, 1.0, [[0, 1], [1, 7]]), "NEIGHBOURS holds actuator indices from 0 to 7"),
])
def test_filters_that_cannot_run_are_refused_before_anything_is_allocated(args, message):
    with pytest.raises(FilterFileError) as info:
        PredictiveFilter(*args)
    assert message in str(info.value)


def test_a_filter_that_cannot_run_is_not_exported(small_scenario, tmp_path):
    spec = HistorySpec("open_loop", 2, 2)
    net = random_filter(small_scenario.grid, spec, "per_actuator")
    with torch.no_grad():
        net.weight.fill_(float("nan"))
    with pytest.raises(ConfigError, match="non-finite coefficient"):
        export_filter(net, spec, tmp_path / "nan.fits")
    with pytest.raises(ConfigError, match="dm_gain_model=-1.0 is invalid"):
        export_filter(random_filter(small_scenario.grid, spec, "per_actuator"), spec, tmp_path / "g.fits",
                      dm_gain_model=-1.0)
    assert not list(tmp_path.glob("*.fits"))
