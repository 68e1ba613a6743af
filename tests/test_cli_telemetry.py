"""identify, fit --telemetry, replay and export through the command line, on telemetry eofnn simulate wrote."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from eofnn.runtime import PredictiveFilter

pytestmark = pytest.mark.cli

TINY_SCENARIO = Path(__file__).parent / "conf" / "tiny_scenario.yaml"


def simulate(cli, out: Path, seed: int, dither_nm: float = 10.0) -> None:
    code, err = cli("simulate", "--scenario", TINY_SCENARIO, "--scenario.plant.dm_gain", "2.0",
                    "--scenario.plant.wfs_noise_nm", "2.0", "--predictor.controller", "dithered_integrator",
                    "--predictor.gain", "0.3", "--predictor.data.dither_nm", dither_nm, "--frames", "3000",
                    "--seed", seed, "--out", out)
    assert code == 0, err


@pytest.mark.slow
def test_identify_fit_replay_export(tmp_path, cli, cli_error):
    recorded, held_out = tmp_path / "run.fits", tmp_path / "held_out.npz"
    simulate(cli, recorded, 1)
    simulate(cli, held_out, 2)
    code, err = cli("identify", "--telemetry", recorded, "--out", tmp_path / "plant.json")
    assert code == 0, err
    plant = json.loads((tmp_path / "plant.json").read_text())
    assert plant["identified"] and abs(plant["dm_gain"] - 2.0) < 0.04 and plant["lag_frames"] == 0

    code, err = cli("fit", "--telemetry", f"[{recorded}]", "--plant", tmp_path / "plant.json",
                    "--predictor.history", "open_loop", "--predictor.history_length", "4",
                    "--predictor.data.val_frames", "500", "--out", tmp_path / "ol.ckpt")
    assert code == 0, err
    assert '"targets": "telemetry"' in err and (tmp_path / "ol.ckpt.yaml").exists()

    code, err = cli("replay", "--checkpoint", tmp_path / "ol.ckpt", "--telemetry", f"[{held_out}]",
                    "--plant", tmp_path / "plant.json", "--settle_frames", "100", "--out", tmp_path / "replay")
    assert code == 0, err
    result = json.loads((tmp_path / "replay" / "replay.json").read_text())
    assert result["predictor"]["median_rms_nm"] < 0.5 * result["own_controller"]["median_rms_nm"]
    assert (tmp_path / "replay" / "replay.png").read_bytes()[:4] == b"\x89PNG"

    code, err = cli("export", "--checkpoint", tmp_path / "ol.ckpt", "--out", tmp_path / "filter.fits")
    assert code == 0, err
    runtime = PredictiveFilter.from_file(tmp_path / "filter.fits")
    assert runtime.n_actuators == 80 and abs(runtime.dm_gain_model - 2.0) < 0.04

    # Identification on the fly (--plant identify is the default), and outputs are never replaced unasked.
    code, err = cli("fit", "--telemetry", f"[{recorded}]", "--out", tmp_path / "ol.ckpt")
    assert code == 2 and "exists" in err

    # Values that cannot mean what they say, and artefacts that do not fit each other: one line each.
    other = tmp_path / "other.npz"  # another system: 9 actuators across
    code, err = cli("simulate", "--scenario", TINY_SCENARIO, "--scenario.grid.n_across", "9", "--frames",
                    "400", "--out", other)
    assert code == 0, err
    for args, message in [
        (("replay", "--checkpoint", tmp_path / "ol.ckpt", "--telemetry", held_out, "--start", "-50", "--out",
          tmp_path / "r1"), "start=-50 is invalid"),
        (("export", "--checkpoint", tmp_path / "ol.ckpt", "--dm_gain_model", "-1", "--out", tmp_path / "f1.fits"),
         "dm_gain_model=-1.0 is invalid"),
        (("replay", "--checkpoint", tmp_path / "ol.ckpt", "--telemetry", other, "--plant", "nominal", "--out",
          tmp_path / "r2"), "was trained for 80 actuators but the telemetry has 69"),
        (("fit", "--telemetry", other, "--plant", tmp_path / "plant.json", "--out", tmp_path / "o.ckpt"),
         "was identified for 80 actuators but the telemetry has 69"),
    ]:
        cli_error(args, message, args[-1])


def test_undithered_telemetry_and_bad_files(tmp_path, cli, cli_error):
    quiet = tmp_path / "quiet.fits"
    simulate(cli, quiet, 3, dither_nm=0.0)
    code, err = cli("identify", "--telemetry", f"[{quiet}]", "--out", tmp_path / "plant.json")
    assert code == 0 and "warning: the telemetry holds no excitation" in err
    assert json.loads((tmp_path / "plant.json").read_text())["identified"] is False
    code, err = cli("fit", "--telemetry", f"[{quiet}]", "--out", tmp_path / "x.ckpt")
    assert code == 2 and "not identified" in err
    # A dither drowned in the WFS noise identifies a DM gain of any size and sign: refused where it would be used
    # (it had been turned into a replay error of 143 um, or "dm_gain=231 is invalid").
    faint = tmp_path / "faint.fits"
    simulate(cli, faint, 5, dither_nm=1e-4)
    cli_error(["fit", "--telemetry", f"[{faint}]", "--out", tmp_path / "f.ckpt"],
              "the plant identified from this telemetry is unusable", alone=False)
    (tmp_path / "junk.fits").write_bytes(b"junk" * 100)
    for command in (["identify", "--out", tmp_path / "p.json"], ["fit", "--out", tmp_path / "y.ckpt"]):
        cli_error([*command, "--telemetry", f"[{tmp_path / 'junk.fits'}]"], "not readable as fits", alone=False)
