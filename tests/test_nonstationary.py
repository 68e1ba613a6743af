"""Non-stationary scenarios: atmosphere changes and a DM gain drift in the simulator, and the re-convergence metric."""

from __future__ import annotations

import json
import math

import pytest
import torch
import yaml

from eofnn.cli.main import main
from eofnn.control.baselines import Integrator
from eofnn.errors import ConfigError
from eofnn.evaluation.metrics import LoopMetrics
from eofnn.evaluation.nonstationary import Change, reconvergence
from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Plant, run_loop
from eofnn.sim.scenario import Scenario

RATE = 1000.0
#: A short outer scale keeps the exact screens small (fast); frozen flow does not depend on it.
BASE = {"r0_m": 0.1, "r0_wavelength_m": 500e-9, "outer_scale_m": 5.0, "model": "exact", "screen_frames": 1024}


def atmosphere(changes=(), layers=None, **kw) -> Atmosphere:
    return Atmosphere(**{**BASE, **kw}, layers=layers or [Layer(1.0, 5.0, 0.0)], changes=list(changes))


def turbulence(atm: Atmosphere, seed: int = 3, n_realisations: int = 1):
    return Scenario(ActuatorGrid(2.0, 10), atm, RATE, Plant()).turbulence(seed, "test", n_realisations)


def structure(s: torch.Tensor, lag: int) -> float:
    """Mean squared difference of frames ``lag`` apart (over frames, actuators and realisations)."""
    return float((s[:, lag:] - s[:, :-lag]).pow(2).mean())


@pytest.mark.physics
def test_wind_speed_change_at_the_asked_frame_and_the_lag_scales_as_one_over_v():
    change = {"at_s": 0.5, "layer": 0, "wind_speed_mps": 20.0}
    s = turbulence(atmosphere([change]), n_realisations=2).frames(0, 1000)
    stationary = turbulence(atmosphere(), n_realisations=2).frames(0, 1000)
    assert torch.equal(s[:, :500], stationary[:, :500])  # frame 499 is the last before at_s
    assert not torch.allclose(s[:, 500], stationary[:, 500])
    before, after = s[:, :500], s[:, 500:]
    # Frozen flow at 4x the speed: lag L after the change moves the screen as far as lag 4L before it.
    assert structure(after, 5) / structure(before, 20) == pytest.approx(1.0, abs=0.25)
    assert structure(after, 5) / structure(before, 5) > 5  # theory for r << L0: 4^(5/3) = 10
    # An independent screen of the same layer: the same variance.
    assert float(after.pow(2).mean() / before.pow(2).mean()) == pytest.approx(1.0, abs=0.3)


def test_strength_change_scales_the_same_screen_over_the_ramp():
    change = {"at_s": 0.2, "layer": 0, "cn2_scale": 4.0, "ramp_s": 0.1}
    s = turbulence(atmosphere([change])).frames(0, 400)[0]
    stationary = turbulence(atmosphere()).frames(0, 400)[0]
    ratio = (s * stationary).sum(-1) / stationary.pow(2).sum(-1)
    u = ((torch.arange(400, dtype=torch.float64) / RATE - 0.2) / 0.1).clamp(0, 1)
    p = u * u * (3 - 2 * u)  # smoothstep
    torch.testing.assert_close(ratio, (1 + 3 * p).sqrt(), rtol=1e-9, atol=0)  # amplitude sqrt(c): 2 after the ramp
    torch.testing.assert_close(s, ratio[:, None] * stationary, rtol=0, atol=1e-9)


def test_any_chunking_and_any_start_give_the_same_frames():
    changes = [{"at_s": 0.3, "layer": 0, "wind_direction_deg": 90.0, "ramp_s": 0.05},
               {"at_s": 0.4, "layer": 1, "wind_speed_mps": 12.0, "cn2_scale": 0.5, "ramp_s": 0.1},
               {"at_s": 0.6, "layer": 0, "wind_speed_mps": 8.0}]
    atm = atmosphere(changes, layers=[Layer(0.6, 5.0, 0.0), Layer(0.4, 8.0, 90.0)])
    late = turbulence(atm).frames(650, 900)  # a fresh stream asked first for frames after every change
    stream = turbulence(atm)
    chunked = torch.cat([c for _, c in stream.chunks(900, 77)], 1)
    torch.testing.assert_close(chunked[:, 650:], late, rtol=0, atol=1e-9)  # PTT projection rounds per chunk
    torch.testing.assert_close(stream.frames(0, 900), chunked, rtol=0, atol=1e-9)
    changing = stream._strips[0][0]
    weights = torch.stack(changing.screen_weights(torch.arange(900)))
    torch.testing.assert_close(weights.pow(2).sum(0), torch.ones(900, dtype=torch.float64))  # variance kept
    assert int((weights > 0).sum(0).max()) == 2 and bool((weights[:2, 301:350] > 0).all())


@pytest.mark.physics
def test_wind_change_is_a_variance_preserving_cross_fade_to_the_new_screen():
    """Over the ramp: cos(pi/2 p) times the old layer plus sin(pi/2 p) times the new screen, which a change with
    no ramp switches to at once (the same screen: its seed is the change's index); p a smoothstep of time."""
    change = {"at_s": 0.3, "wind_direction_deg": 90.0}
    ramped = turbulence(atmosphere([dict(change, ramp_s=0.1)])).frames(0, 500)
    switched = turbulence(atmosphere([change])).frames(0, 500)
    stationary = turbulence(atmosphere()).frames(0, 500)
    u = ((torch.arange(500, dtype=torch.float64) / RATE - 0.3) / 0.1).clamp(0, 1).view(1, -1, 1)
    p = u * u * (3 - 2 * u)  # smoothstep: the weights' slope is continuous at both ends of the ramp
    expected = torch.cos(math.pi / 2 * p) * stationary + torch.sin(math.pi / 2 * p) * switched
    torch.testing.assert_close(ramped, expected, rtol=0, atol=1e-9)
    assert torch.equal(ramped[:, :301], stationary[:, :301]) and torch.equal(ramped[:, 400:], switched[:, 400:])


def test_dm_gain_drift_follows_the_ramp():
    drift = {"start_s": 0.1, "stop_s": 0.3, "to": 1.5}
    scenario = Scenario(ActuatorGrid(2.0, 10), atmosphere(), RATE, Plant(dm_gain=0.8, dm_gain_drift=drift))
    result = run_loop(scenario.turbulence(1), scenario.plant, Integrator(0.3), 400, record=("s", "y", "eps"))
    t = result.telemetry
    frames = torch.arange(10, 400)
    gain = ((t.eps - t.s) * t.y).sum(-1)[0, frames] / t.y.pow(2).sum(-1)[0, frames]
    expected = 0.8 + 0.7 * ((frames.to(torch.float64) / RATE - 0.1) / 0.2).clamp(0, 1)
    torch.testing.assert_close(gain, expected, rtol=1e-12, atol=0)


def test_no_change_and_no_drift_are_the_stationary_stream_and_plant():
    assert atmosphere().changes == [] and Plant().dm_gain_drift is None
    scenario = Scenario.from_dict({"atmosphere": {**BASE, "changes": []}, "plant": {"dm_gain_drift": None}})
    assert scenario.to_dict()["atmosphere"]["changes"] == [] and scenario.to_dict()["plant"]["dm_gain_drift"] is None


@pytest.mark.parametrize("changes, match", [
    ([{"at_s": -1.0, "wind_speed_mps": 3.0}], "at_s=-1.0 is invalid"),
    ([{"at_s": 1.0, "layer": 2, "wind_speed_mps": 3.0}], "layer=2 is invalid: the atmosphere has 1 layer"),
    ([{"at_s": 1.0}], "changes nothing"),
    ([{"wind_speed_mps": 3.0}], "has no at_s"),
    ([{"at_s": 1.0, "speed": 3.0}], "unknown key(s) speed in atmosphere.changes"),
    ([{"at_s": 1.0, "ramp_s": -0.1, "cn2_scale": 2.0}], "ramp_s=-0.1 is invalid"),
    ([{"at_s": 1.0, "cn2_scale": 0.0}], "cn2_scale=0.0 is invalid"),
    ([{"at_s": 1.0, "ramp_s": 0.5, "cn2_scale": 2.0}, {"at_s": 1.2, "wind_speed_mps": 3.0}], "overlap"),
    ([{"at_s": 1.0, "wind_direction_deg": float("nan")}], "wind_direction_deg=nan is invalid"),
    ([{"at_s": 1.0, "wind_speed_mps": 0.0}], "wind_speed_mps=0.0 is invalid for model 'exact'"),
    ({"at_s": 1.0}, "give a list of changes"),
])
def test_bad_changes_are_one_line_errors(changes, match):
    with pytest.raises(ConfigError, match=None) as err:
        Scenario.from_dict({"atmosphere": {**BASE, "changes": changes}})
    assert match in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("drift, match", [
    ({"start_s": 2.0, "stop_s": 1.0, "to": 1.5}, "stop_s=1.0 is invalid: it must be at least start_s=2.0"),
    ({"start_s": -1.0, "stop_s": 1.0, "to": 1.5}, "start_s=-1.0 is invalid"),
    ({"start_s": 0.0, "stop_s": 1.0, "to": 0.0}, "to=0.0 is invalid"),
    ({"start_s": 0.0, "stop_s": 1.0}, "it needs to"),
    ({"start_s": 0.0, "stop_s": 1.0, "to": 1.5, "from": 1.0}, "unknown key(s) from"),
    (1.5, "give {start_s, stop_s, to}"),
])
def test_bad_drifts_are_one_line_errors(drift, match):
    with pytest.raises(ConfigError) as err:
        Scenario.from_dict({"plant": {"dm_gain_drift": drift}})
    assert match in str(err.value) and "\n" not in str(err.value)


@pytest.mark.cli
def test_bad_change_on_the_command_line_is_one_line(cli_error, tmp_path):
    cli_error(["compare", "--scenario.atmosphere.changes", "[{at_s: 1.0, layer: 3, cn2_scale: 2.0}]",
               "--predictors", "{i: {controller: integrator}}", "--out", tmp_path / "o"], "layer=3 is invalid")


def test_reconvergence_definition():
    """Reference: the best settled median; re-converged when the 200-frame running median is within 10%."""
    n = torch.arange(3000)
    fast = torch.where(n < 1300, 20.0, 5.0)  # the change ends at frame 1000; settles at 5 nm from frame 1300
    slow = torch.full((3000,), 5.2)
    never = torch.where(n < 1000, 5.0, 8.0)
    out = reconvergence({"fast": fast.tolist(), "slow": slow.tolist(), "never": never.tolist(), "gone": None},
                        [Change("c", 900, 1000)], RATE)
    assert out["fast"][0]["reference"] == "fast" and out["fast"][0]["reference_rms_nm"] == 5.0
    # A 200-frame window [i, i + 200) after frame 1000 has i - 100 values of 5; its (lower) median is 5 from i = 200.
    assert out["fast"][0]["reconvergence_frames"] == 400 and out["fast"][0]["reconvergence_s"] == 0.4
    assert out["slow"][0]["reconvergence_frames"] == 200 and out["slow"][0]["median_rms_after_nm"] == pytest.approx(5.2)
    assert out["never"][0]["reconvergence_frames"] is None and out["never"][0]["median_rms_after_nm"] == 8.0
    assert out["never"][0]["median_rms_before_nm"] == 5.0 and out["fast"][0]["median_rms_before_nm"] == 20.0
    assert out["gone"][0]["reconvergence_frames"] is None and out["gone"][0]["median_rms_after_nm"] is None
    assert "reconvergence" not in LoopMetrics(1.0, 1.0, 1.0, 1.0, False, None, 0, 10).summary()  # stationary runs


@pytest.mark.cli
@pytest.mark.slow
def test_compare_with_a_change_reports_reconvergence(tmp_path):
    config = {
        "scenario": {"grid": {"diameter_m": 2.0, "n_across": 10}, "frame_rate_hz": RATE,
                     "atmosphere": {**BASE, "screen_frames": 1500, "layers": [{"wind_speed_mps": 5.0}],
                                    "changes": [{"at_s": 0.6, "layer": 0, "wind_speed_mps": 15.0, "ramp_s": 0.05}]},
                     "plant": {"delay_frames": 2, "wfs_noise_nm": 1.0,
                               "dm_gain_drift": {"start_s": 1.0, "stop_s": 1.1, "to": 1.1}}},
        "predictors": {"integrator": {"controller": "integrator", "gain": 0.5},
                       "rls": {"history": "open_loop", "history_length": 3, "adaptation": {"method": "rls"},
                               "data": {"frames": 500, "val_frames": 100, "sequence_frames": 500}}},
        "evaluation": {"frames": 1500, "settle_frames": 100, "psd_segment_frames": 256},
    }
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(config))
    assert main(["compare", "--config", str(path), "--out", str(tmp_path / "o")]) == 0
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())["scenarios"]["nominal"]
    for name in ("integrator", "rls"):
        entries = metrics[name]["reconvergence"]
        assert [e["change"] for e in entries] == ["atmosphere.changes[0]", "plant.dm_gain_drift"]
        assert [e["end_s"] for e in entries] == [0.65, 1.1]
        assert entries[0]["reference"] in ("integrator", "rls") and entries[0]["reference_rms_nm"] > 0
        frames = entries[0]["reconvergence_frames"]
        assert frames is None or 200 <= frames <= 350  # the window's 200 frames at least; the segment is 350 long
