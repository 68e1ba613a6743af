from __future__ import annotations

from pathlib import Path

import pytest

from eofnn.cli.main import main
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Plant
from eofnn.sim.scenario import Scenario


@pytest.fixture
def small_scenario() -> Scenario:
    """A 2 m telescope with 10 actuators across (76 active), one fast layer: loops run in milliseconds.

    The default physics (exact frozen flow seen through each subaperture); streams up to 4096 frames.
    """
    return Scenario(
        grid=ActuatorGrid(2.0, 10),
        atmosphere=Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=(Layer(1.0, 10.0, 0.0),),
                              screen_frames=4096),
        frame_rate_hz=1000.0,
        plant=Plant(delay_frames=2),
    )


@pytest.fixture
def cli(capsys):
    """eofnn's command line run in this process: ``cli(*args)`` gives (exit code, what it wrote on stderr)."""

    def run(*args) -> tuple[int, str]:
        code = main([str(a) for a in args])
        return code, capsys.readouterr().err

    return run


@pytest.fixture
def clean_and_noisy_telemetry(cli, tmp_path):
    """``tmp_path`` holding dithered-integrator telemetry of the tiny scenario (1500 frames, gain 0.3, 10 nm dither):
    ``clean.npz`` without WFS noise (seed 1) and ``noisy.npz`` with 3 nm of it (seed 2)."""
    scenario = Path(__file__).parent / "conf" / "tiny_scenario.yaml"
    for name, noise, seed in (("clean.npz", 0.0, 1), ("noisy.npz", 3.0, 2)):
        code, err = cli("simulate", "--scenario", scenario, "--scenario.plant.wfs_noise_nm", noise,
                        "--predictor.controller", "dithered_integrator", "--predictor.gain", "0.3",
                        "--predictor.data.dither_nm", "10.0", "--frames", "1500", "--seed", seed,
                        "--out", tmp_path / name)
        assert code == 0, err
    return tmp_path


@pytest.fixture
def cli_error(cli):
    """``cli_error(args, expected, out)`` runs a command that must be refused and gives its error line.

    Refused means exit code 2, one line ``eofnn: error: ...`` that holds ``expected``, no traceback, and nothing
    written at ``out`` (when given).  ``alone=False`` lets other lines written before the refusal (a command's
    progress or notes) stand beside the error line; there must still be exactly one error line.
    """

    def refused(args, expected: str = "", out: Path | str | None = None, *, alone: bool = True) -> str:
        code, err = cli(*args)
        lines = err.strip().splitlines()
        errors = [line for line in lines if line.startswith("eofnn: error:")]
        assert code == 2, err
        assert len(errors) == 1 and (not alone or len(lines) == 1), err
        assert "Traceback" not in err, err
        assert expected in errors[0], errors[0]
        assert out is None or not Path(out).exists(), f"{out} was written: {err}"
        return errors[0]

    return refused
