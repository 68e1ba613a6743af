"""examples/oopao_loop.py's options: a point of the OOPAO map (``--photon-noise``), the full decomposition
(``--aliasing``) and the anti-aliasing study (``--anti-aliasing``) are one or another, and too few frames are refused;
each in one line before anything is simulated."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "oopao_loop.py"


@pytest.mark.cli
@pytest.mark.parametrize("argv, said", [
    (["--photon-noise", "--aliasing"], ("--photon-noise", "--aliasing", "give one of them")),
    (["--anti-aliasing", "--aliasing"], ("--anti-aliasing", "--aliasing", "give one of them")),
    (["--small", "--frames", "500"], ("settle_frames=300 is invalid",)),
    (["--small", "--eofnn-trained"], ("--eofnn-trained", "give --anti-aliasing too")),
    (["--small", "--anti-aliasing", "--own-noise"], ("--own-noise", "give --eofnn-trained too")),
    (["--small", "--anti-aliasing", "--all-modes", "--static-gain"], ("--all-modes and --static-gain",
                                                                       "give --eofnn-trained too")),
    (["--small", "--anti-aliasing", "--static-gain"], ("--static-gain", "give --eofnn-trained too")),
    (["--small", "--anti-aliasing", "--radius", "0.1"], ("radius=0.1 is invalid",)),
    (["--small", "--anti-aliasing", "--eofnn-trained", "--wind-direction", "nan"], ("nan deg is not mapped",)),
    (["--small", "--twin-identified"], ("--twin-identified", "give --anti-aliasing too")),
    (["--small", "--anti-aliasing", "--twin-identified", "--twin-record-frames", "900"],
     ("--twin-record-frames=900 is invalid", "at least 1200")),
    (["--small", "--anti-aliasing", "--layers", "0.7:20"], ("'0.7:20' is invalid", "FRACTION:SPEED:DIRECTION")),
    (["--small", "--anti-aliasing", "--layers", "0.7:20:30,0.7:10:0"], ("layers=", "sum to 1")),
    (["--small", "--no-oracle"], ("--no-oracle", "give --anti-aliasing too")),
    (["--small", "--scored-frames", "2000"], ("--scored-frames", "give --anti-aliasing too")),
    (["--small", "--anti-aliasing", "--scored-frames", "100"], ("--scored-frames=100 is invalid", "at least 128")),
    (["--small", "--sensor", "pyramid", "--aliasing"], ("--aliasing is invalid with --sensor pyramid",)),
    (["--small", "--sensor", "pyramid", "--anti-aliasing", "--eofnn-trained"],
     ("--eofnn-trained is invalid with --sensor pyramid",)),
    (["--small", "--modulation", "4"], ("--modulation 4 is invalid with --sensor shack_hartmann",)),
    (["--small", "--sensor", "pyramid", "--modulation", "30", "--frames", "1000"],
     ("modulation_lambda_over_d=30.0 is invalid",)),
])
def test_options_that_cannot_run_are_refused_in_one_line(capsys, argv, said):
    spec = importlib.util.spec_from_file_location("oopao_loop", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    with pytest.raises(SystemExit) as exit_:
        example.main(argv)
    assert exit_.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert all(part in error for part in said), error
