"""``eofnn twin --optical_gain``: the sensor's optical gain on sky, which the dither cannot tell from the DM's gain
(it identifies their product), divides the POL before the seeing; without it r0 is of the sensor's reading of the
phase (``optical_gain^(-6/5)`` high), with a one-line warning."""

from __future__ import annotations

import pytest
from test_twin import recorded  # noqa: F401  (the fixture: test_twin.py's dithered record)

from eofnn.errors import ConfigError
from eofnn.telemetry.record import TELEMETRY_REQUIRED, Telemetry
from eofnn.training.twin import identify_twin

OPTICAL_GAIN = 0.8


@pytest.fixture(scope="module")
def records(recorded):  # noqa: F811
    """test_twin.py's dithered record as recorded and as a sensor of optical gain 0.8 would have read it (its wfs
    times 0.8: the loop's gain is then the product)."""
    t = Telemetry.load(recorded, required=TELEMETRY_REQUIRED)

    def record(scale: float) -> Telemetry:
        return Telemetry(y=t.y, wfs=t.wfs * scale, delay_frames=t.delay_frames, frame_rate_hz=t.frame_rate_hz,
                         positions_m=t.positions_m)
    return record(1.0), record(OPTICAL_GAIN)


@pytest.mark.slow
def test_the_optical_gain_given_recovers_the_phases_r0_and_the_dms_gain(records):
    plain, read = records
    truth = identify_twin(plain)
    given = identify_twin(read, optical_gain=OPTICAL_GAIN)
    for name in ("r0_m", "outer_scale_m", "wfs_noise_nm"):
        assert given.value(name) == pytest.approx(truth.value(name), rel=1e-6), name
    assert given.value("dm_gain") == pytest.approx(OPTICAL_GAIN * truth.value("dm_gain"), rel=1e-6)  # the product
    assert given.twin_config()["plant"]["dm_gain"] == pytest.approx(truth.twin_config()["plant"]["dm_gain"], abs=1e-4)
    assert [lay["speed_mps"] for lay in given.layers] == pytest.approx([lay["speed_mps"] for lay in truth.layers])
    # Without it, r0 is the sensor's reading: high by about optical_gain^(-6/5) (L0 chosen from a grid may move it).
    sensed = identify_twin(read)
    assert any("give optical_gain" in w for w in sensed.warnings)
    assert not any("give optical_gain" in w for w in given.warnings)
    assert sensed.value("r0_m") / truth.value("r0_m") == pytest.approx(OPTICAL_GAIN ** -1.2, rel=0.05)


def test_an_optical_gain_out_of_range_is_refused_in_one_line(records):
    for bad in (-0.5, "measured"):
        with pytest.raises(ConfigError, match=f"optical_gain={bad!r}"):
            identify_twin(records[0], optical_gain=bad)


@pytest.mark.slow
def test_identified_takes_the_whole_product_as_the_sensors(records):
    """Where the DM's gain is its interaction matrix's, the dither's product is the optical gain: the phase's r0 again,
    the twin's DM gain 1."""
    plain, read = records
    truth, found = identify_twin(plain), identify_twin(read, optical_gain="identified")
    assert found.value("optical_gain") == pytest.approx(found.value("dm_gain"))
    assert found.value("r0_m") / truth.value("r0_m") == pytest.approx(truth.value("dm_gain") ** 1.2, rel=0.03)
    assert found.twin_config()["plant"]["dm_gain"] == 1.0



@pytest.mark.cli
def test_the_cli_refuses_a_bad_optical_gain_in_one_line_before_importing_anything_heavy():
    from test_help_speed import imported

    answer = imported(["twin", "--telemetry", "x.npz", "--optical_gain", "abc", "--out", "o"])
    assert answer["heavy"] == [] and answer["code"] == 2, answer
    assert "optical_gain='abc' is invalid" in answer["stderr"] and "identified" in answer["stderr"]
