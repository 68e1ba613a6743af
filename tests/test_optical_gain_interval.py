"""A pyramid's analytic stability margins as an interval of optical gain as well as of DM gain
(:func:`eofnn.analysis.linear.optical_gain_interval`): in metrics.json and the verdict of a pyramid compare."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from eofnn.analysis.linear import optical_gain_interval, summary
from eofnn.analysis.stability import LoopSetup, analyse_integrator
from eofnn.cli.main import main
from eofnn.reporting.verdict import _optical_gain_text
from eofnn.sim.loop.plant import Plant

ROOT = Path(__file__).resolve().parents[1]


def _summary(gain: float, dm_gain: float) -> dict:
    return summary(analyse_integrator(gain, 0.0, LoopSetup.from_plant(Plant(delay_frames=2, dm_gain=dm_gain))))


def test_the_optical_gain_interval_is_the_dm_gain_interval_over_the_nominal_dm_gain():
    """An integrator of gain 0.5 with two frames of delay is stable for a loop gain below 1 (critical gain 1): at a
    DM gain of 1.25 its DM-gain interval is 0 to 2, so the pyramid's optical gain may range over 0 to 2 / 1.25."""
    stability = _summary(0.5, 1.25)
    assert stability["dm_gain_interval"][1] == pytest.approx(2.0, rel=1e-6)
    plain = optical_gain_interval(stability, 1.25)
    assert plain["relative_interval"][0] == 0.0 and plain["relative_interval"][1] == pytest.approx(1.6, rel=1e-6)
    assert plain["interval"] == plain["relative_interval"] and plain["assumed"] == 1.0
    assert "compensation_range" not in plain
    # Compensated: the loop gain of mode m is g og_m / c_m, so og_m / c_m has the relative interval.
    compensated = optical_gain_interval(stability, 1.25, [0.4, 0.5, 0.6])
    assert compensated["relative_interval"] == plain["relative_interval"]
    assert compensated["assumed"] == pytest.approx(0.5) and compensated["compensation_range"] == [0.4, 0.6]
    assert compensated["interval"][1] == pytest.approx(0.8, rel=1e-6)
    assert _optical_gain_text(plain) == ("optical gain 0 to 1.6 (uncompensated: relative to the pyramid's response "
                                         "about a flat wavefront)")
    # An unstable loop (gain 1.5 at DM gain 1: loop gain above critical) has no interval.
    assert optical_gain_interval(_summary(1.5, 1.0), 1.0) is None


@pytest.mark.slow
@pytest.mark.cli
def test_a_pyramid_compare_states_each_margin_in_optical_gain(cli, tmp_path):
    """tests/conf/pyr_tiny.yaml's pyramid with its optical gains compensated, one integrator (gain 0.5), analytic
    stability on: metrics.json and the verdict carry the optical-gain interval beside the DM-gain one."""
    config = yaml.safe_load((ROOT / "tests" / "conf" / "pyr_tiny.yaml").read_text())
    config["scenario"]["sensor"]["optical_gain_compensation"] = True
    config["predictors"] = {"integrator": {"controller": "integrator", "gain": 0.5}}
    config["evaluation"].update(frames=150, settle_frames=50, psd_segment_frames=64, analytic_stability=True)
    path = tmp_path / "pyr.yaml"
    path.write_text(yaml.safe_dump(config))
    code, err = cli("compare", "--config", path, "--out", tmp_path / "o")
    assert code == 0, err
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    stability = metrics["stability"]["nominal"]["integrator"]
    og = stability["optical_gain"]
    assert og["relative_interval"][1] == pytest.approx(stability["dm_gain_interval"][1], rel=1e-9)  # DM gain 1
    low, high = og["compensation_range"]
    assert 0 < low <= og["assumed"] <= high < 1  # the compensation's gains about its integrator's residual
    assert og["interval"][1] == pytest.approx(og["relative_interval"][1] * og["assumed"], rel=1e-9)
    assert metrics["verdict"]["scenarios"]["nominal"]["best_classical"]["stability"]["optical_gain"] == og
    verdict = (tmp_path / "o" / "results.md").read_text()
    assert (f"integrator: 0 to 2 (linear analysis); optical gain 0 to 2 times the gain the compensation divides each "
            f"mode by ({low:.3g} to {high:.3g}; at their mean {og['assumed']:.3g}: 0 to ") in verdict


@pytest.mark.cli
def test_eofnn_stability_states_a_pyramids_optical_gain_interval(tmp_path, capsys):
    """``eofnn stability`` of an integrator (gain 0.5) in tests/conf/pyr_tiny.yaml's pyramid scenario, uncompensated:
    the optical gain may range over the DM-gain interval, 0 to 2; a Shack-Hartmann scenario has no such interval."""
    scenario = yaml.safe_load((ROOT / "tests" / "conf" / "pyr_tiny.yaml").read_text())["scenario"]
    scenario["atmosphere"]["screen_frames"] = 5000  # the command's evaluation frames (no screen is drawn)
    path = tmp_path / "pyr.yaml"
    path.write_text(yaml.safe_dump(scenario))
    assert main(["stability", "--scenario", str(path), "--controller", "{controller: integrator, gain: 0.5}",
                 "--out", str(tmp_path / "s")]) == 0
    line = json.loads(capsys.readouterr().err.strip().splitlines()[-1])
    assert line["optical_gain"]["interval"][1] == pytest.approx(2.0, rel=1e-6)
    assert "compensation_range" not in line["optical_gain"]
    saved = json.loads((tmp_path / "s" / "stability.json").read_text())
    assert saved["optical_gain"] == line["optical_gain"] and saved["dm_gain_interval"][1] == pytest.approx(2.0)
    scenario["sensor"] = {"kind": "shack_hartmann", "samples_per_subaperture": 2}
    path.write_text(yaml.safe_dump(scenario))
    assert main(["stability", "--scenario", str(path), "--controller", "{controller: integrator, gain: 0.5}",
                 "--out", str(tmp_path / "sh")]) == 0
    assert "optical_gain" not in json.loads(capsys.readouterr().err.strip().splitlines()[-1])
