"""examples/oopao_loop.py's options: a point of the OOPAO map (``--photon-noise``) and the full decomposition
(``--aliasing``) are one or the other, refused in one line before anything is simulated."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "oopao_loop.py"


@pytest.mark.cli
def test_photon_noise_and_aliasing_together_are_refused_in_one_line(capsys):
    spec = importlib.util.spec_from_file_location("oopao_loop", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    with pytest.raises(SystemExit) as exit_:
        example.main(["--photon-noise", "--aliasing"])
    assert exit_.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--photon-noise" in error and "--aliasing" in error and "give one of them" in error
