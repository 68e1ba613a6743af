"""A predictor used in conditions other than its training's says so in one line (``eofnn.training.conditions``)."""

from __future__ import annotations

import json
import re

import pytest

from eofnn.training.conditions import TOLERANCES, Conditions, shift_warnings


def _conditions(noise=0.0, gain=1.0, winds=(10.0,), source="scenario") -> Conditions:
    return Conditions(noise, gain, winds, source)


def test_a_noise_free_predictor_on_noisy_data_is_named_with_both_noise_levels():
    lines = shift_warnings(_conditions(0.0), _conditions(2.0, source="identified"), "replay of cl.ckpt")
    assert len(lines) == 1
    assert "trained at 0 nm of WFS noise (scenario), used at 2 nm (identified)" in lines[0]
    assert "passes it back" in lines[0] and "\n" not in lines[0]


@pytest.mark.parametrize("trained, now, shifted", [
    (_conditions(0.1), _conditions(0.2), False),  # a factor 2 but 0.1 nm: no shift that matters
    (_conditions(2.0), _conditions(2.9), False),  # 0.9 nm but a factor 1.45
    (_conditions(2.0), _conditions(3.1), True),
    (_conditions(3.0), _conditions(0.0), True),  # less noise than trained for: lag for nothing
    (_conditions(gain=1.0), _conditions(gain=1.08), False),
    (_conditions(gain=1.0), _conditions(gain=2.0), True),
    (_conditions(winds=(10.0,)), _conditions(winds=(12.0,)), False),
    (_conditions(winds=(10.0,)), _conditions(winds=(20.0, 30.0)), True),
    (_conditions(winds=(10.0,)), _conditions(winds=None), False),  # telemetry does not tell the wind
    (_conditions(noise=None), _conditions(5.0), False),
])
def test_what_counts_as_a_shift(trained, now, shifted):
    assert bool(shift_warnings(trained, now, "x")) is shifted


def test_a_checkpoint_without_recorded_conditions_warns_nothing():
    assert shift_warnings(Conditions.from_dict(None), _conditions(5.0), "x") == []
    assert Conditions.from_dict(_conditions(1.0, 2.0, (3.0,)).to_dict()) == _conditions(1.0, 2.0, (3.0,))
    assert TOLERANCES["wfs_noise_factor"] > 1


@pytest.mark.cli
@pytest.mark.slow
def test_replay_of_a_noise_free_fit_on_noisy_telemetry_warns_in_one_line(cli, tmp_path, clean_and_noisy_telemetry):
    """Fitted on noise-free telemetry, replayed on telemetry with 3 nm of WFS noise: one ``eofnn: warning:`` line
    naming both noise levels (identified from each file), and the same line in replay.json."""
    code, err = cli("fit", "--telemetry", f"[{tmp_path / 'clean.npz'}]", "--predictor.history", "closed_loop",
                    "--predictor.history_length", "3", "--predictor.data.val_frames", "300",
                    "--out", tmp_path / "cl.ckpt")
    assert code == 0, err
    code, err = cli("replay", "--checkpoint", tmp_path / "cl.ckpt", "--telemetry", f"[{tmp_path / 'noisy.npz'}]",
                    "--settle_frames", "100", "--out", tmp_path / "replay")
    assert code == 0, err
    warned = [line for line in err.splitlines() if line.startswith("eofnn: warning:") and "WFS noise" in line]
    assert len(warned) == 1, err
    trained, used = map(float, re.search(r"trained at ([\d.e+-]+) nm of WFS noise .* used at ([\d.e+-]+) nm",
                                         warned[0]).groups())
    assert trained < 1.0 and 2.4 < used < 3.6, warned[0]  # identify finds ~0.48 nm in noise-free telemetry
    assert json.loads((tmp_path / "replay" / "replay.json").read_text())["shift"] == [
        warned[0].removeprefix("eofnn: warning: ")]
    # The same fit replayed on noise-free telemetry of its own kind says nothing.
    code, err = cli("replay", "--checkpoint", tmp_path / "cl.ckpt", "--telemetry", f"[{tmp_path / 'clean.npz'}]",
                    "--settle_frames", "100", "--out", tmp_path / "replay_clean")
    assert code == 0 and not [line for line in err.splitlines() if line.startswith("eofnn: warning:")], err
