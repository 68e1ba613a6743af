"""A record in another unit than eofnn's nm (metres, OOPAO's influence-function peak, volts) is converted on reading:
``--command_unit`` and ``--measurement_unit`` of identify, replay, fit and twin (``eofnn.telemetry.units``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_help_speed import imported

from eofnn.data.targets import in_nm, load_telemetry
from eofnn.errors import ConfigError
from eofnn.sim.sensing.least_squares import surface_per_command
from eofnn.telemetry.units import nm_per_unit


def test_units_name_their_factor_and_anything_else_is_refused_in_one_line():
    assert nm_per_unit("surface", 2.99) == nm_per_unit("nm", 2.99) == 1.0
    assert nm_per_unit("m", 2.99) == 1e9 and nm_per_unit("um", 2.99) == 1e3 and nm_per_unit("peak", 2.99) == 2.99
    assert nm_per_unit("850", 2.99) == 850.0 and nm_per_unit(0.5, 2.99) == 0.5  # nm per volt, from the CLI or YAML
    for bad in ("furlong", "-3", "0", "nan", True, None):
        with pytest.raises(ConfigError, match="unit=.* is invalid: it must be one of surface") as err:
            nm_per_unit(bad, 2.99)
        assert "\n" not in str(err.value)


def _write(path, y, wfs, **extra):
    k = y.shape[-1]
    side = int(round(k ** 0.5))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2) * 0.25
    np.savez(path, y=y, wfs=wfs, positions_m=grid, delay_frames=2, frame_rate_hz=1000.0, **extra)


def test_streamed_and_whole_records_convert_alike(tmp_path):
    rng = np.random.default_rng(0)
    y, wfs = rng.normal(size=(300, 16)), rng.normal(size=(300, 16))
    _write(tmp_path / "a.npz", y, wfs)
    whole, = load_telemetry(tmp_path / "a.npz")
    streamed, = load_telemetry(tmp_path / "a.npz", streamed=True)
    assert in_nm(whole) == (whole, "")  # eofnn's own unit: untouched
    (w, note), (s, _) = in_nm(whole, "peak", "2.5"), in_nm(streamed, "peak", "2.5")
    assert "y multiplied by 2.99" in note and "wfs by 2.5" in note
    torch.testing.assert_close(w.y, torch.as_tensor(y) * surface_per_command(0.35))
    torch.testing.assert_close(w.wfs, torch.as_tensor(wfs) * 2.5)
    torch.testing.assert_close(s.y[0:300], w.y)
    torch.testing.assert_close(s.shifted(2).wfs[10:20], w.wfs[12:22])  # views keep the factor
    s.check()  # the scan still runs over the stored values


@pytest.mark.parametrize("command", ["replay", "identify", "twin"])
def test_an_unknown_unit_is_refused_before_anything_heavy(command):
    args = [command, "--telemetry", "x.npz", "--command_unit", "furlong", "--out", "o"]
    args += ["--checkpoint", "c.ckpt"] if command == "replay" else []
    answer = imported(args)
    assert answer["code"] == 2 and answer["heavy"] == [], answer
    errors = [line for line in answer["stderr"].splitlines() if line.startswith("eofnn: error:")]
    assert len(errors) == 1 and "command_unit='furlong' is invalid: it must be one of surface" in errors[0], answer


def _replay(cli, checkpoint, path, out, *units):
    code, err = cli("replay", "--checkpoint", checkpoint, "--telemetry", f"[{path}]", "--settle_frames", "100",
                    *units, "--out", out)
    assert code == 0, err
    return [line for line in err.splitlines() if line.startswith("eofnn: warning:")], \
        json.loads((out / "replay.json").read_text())


@pytest.mark.cli
@pytest.mark.slow
def test_replay_of_a_record_in_metres_with_its_unit_equals_the_record_in_nm(cli, tmp_path, clean_and_noisy_telemetry):
    """Fitted on 3 nm-noise telemetry; the held-out record written in metres warns of a noise shift (its noise is
    read as 3e-9 nm) unless replay is told ``--command_unit m``: then no warning, and the numbers of the record in
    nm."""
    code, err = cli("fit", "--telemetry", f"[{tmp_path / 'noisy.npz'}]", "--predictor.history", "closed_loop",
                    "--predictor.history_length", "3", "--predictor.data.val_frames", "300",
                    "--out", tmp_path / "cl.ckpt")
    assert code == 0, err
    with np.load(tmp_path / "noisy.npz") as f:
        record = {k: f[k] * 1e-9 if k in ("y", "wfs", "s", "eps") else f[k] for k in f.files}
    np.savez(tmp_path / "metres.npz", **record)
    nm_warnings, in_nm_json = _replay(cli, tmp_path / "cl.ckpt", tmp_path / "noisy.npz", tmp_path / "r_nm")
    assert nm_warnings == []
    m_warnings, _ = _replay(cli, tmp_path / "cl.ckpt", tmp_path / "metres.npz", tmp_path / "r_m")
    assert any("WFS noise" in line for line in m_warnings), m_warnings
    converted_warnings, converted = _replay(cli, tmp_path / "cl.ckpt", tmp_path / "metres.npz", tmp_path / "r_conv",
                                            "--command_unit", "m")
    assert converted_warnings == []
    for key in ("median_rms_nm", "mean_rms_nm", "median_rms_noise_corrected_nm"):
        assert converted["predictor"][key] == pytest.approx(in_nm_json["predictor"][key], rel=1e-6), key
        assert converted["own_controller"][key] == pytest.approx(in_nm_json["own_controller"][key], rel=1e-6), key
    assert converted["noise_nm"] == pytest.approx(in_nm_json["noise_nm"], rel=1e-6)
    assert converted["guard"]["deployed"] == in_nm_json["guard"]["deployed"]
    assert converted["guard"]["gain_nm2"] == pytest.approx(in_nm_json["guard"]["gain_nm2"], rel=1e-6)
