from __future__ import annotations

import numpy as np
import pytest
import torch

from eofnn.control import Integrator
from eofnn.errors import OutputExistsError, TelemetryError
from eofnn.sim import Telemetry, run_loop


@pytest.mark.parametrize("suffix", [".fits", ".npz"])
def test_round_trip(small_scenario, tmp_path, suffix):
    tel = run_loop(small_scenario.turbulence(0, n_realisations=2), small_scenario.plant, Integrator(0.5), 40).telemetry
    tel.config["scenario"] = small_scenario.to_dict()
    path = tel.save(tmp_path / f"run{suffix}")
    back = Telemetry.load(path)
    for name, value in tel.arrays().items():
        assert torch.equal(getattr(back, name), value)
    assert back.delay_frames == 2
    assert back.config["scenario"]["grid"]["n_across"] == 10
    with pytest.raises(OutputExistsError):
        tel.save(path)
    tel.save(path, overwrite=True)


def test_bad_files_give_clear_errors(tmp_path):
    good = np.zeros((10, 5))
    np.savez(tmp_path / "missing.npz", s=good, y=good, eps=good)
    with pytest.raises(TelemetryError, match="lacks array.*wfs"):
        Telemetry.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "shape.npz", s=good, y=good, eps=good, wfs=np.zeros((10, 6)))
    with pytest.raises(TelemetryError, match="'wfs' has shape"):
        Telemetry.load(tmp_path / "shape.npz")
    bad = good.copy()
    bad[3, 2] = np.nan
    np.savez(tmp_path / "nan.npz", s=good, y=good, eps=bad, wfs=good)
    with pytest.raises(TelemetryError, match="'eps' holds 1 non-finite"):
        Telemetry.load(tmp_path / "nan.npz")
    with pytest.raises(TelemetryError, match="does not exist"):
        Telemetry.load(tmp_path / "nothing.fits")
    with pytest.raises(TelemetryError, match="suffix"):
        Telemetry(s=torch.zeros(3, 4)).save(tmp_path / "x.txt")
