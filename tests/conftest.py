from __future__ import annotations

import os
from pathlib import Path

import pytest

# Under pytest-xdist each worker gets its share of the cores for its torch, OpenMP and BLAS threads (2 workers on
# 2 cores: one thread each), set before numpy and torch load here and inherited by the commands tests start. Two
# workers each spinning up threads for every core oversubscribe them: OpenBLAS's and OpenMP's waiting threads spin,
# and on 2 busy cores a 400 x 400 eigvals took 2 s against 0.09 s on one thread. A variable already set is kept.
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    _threads = str(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))
    for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_variable, _threads)

from eofnn.cli.main import main  # noqa: E402
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Plant  # noqa: E402
from eofnn.sim.scenario import Scenario  # noqa: E402


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
