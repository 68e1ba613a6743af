"""examples/hcipy_loop.py: an HCIPy-only loop closed by a filter eofnn trained from that loop's telemetry."""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

import pytest
from astropy.io import fits

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "hcipy_loop.py"


def test_loop_module_uses_no_eofnn_simulator():
    tree = ast.parse(EXAMPLE.read_text())
    top = [node for node in tree.body if isinstance(node, (ast.Import, ast.ImportFrom))]
    modules = {alias.name for node in top if isinstance(node, ast.Import) for alias in node.names}
    modules |= {node.module for node in top if isinstance(node, ast.ImportFrom)}
    assert modules == {"__future__", "argparse", "tempfile", "pathlib", "hcipy", "numpy", "astropy.io", "eofnn.runtime"}


@pytest.mark.cli
@pytest.mark.slow
def test_exported_filter_beats_the_integrator_in_an_hcipy_loop(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("hcipy_loop", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    results = example.main(["--n-across", "8", "--train-frames", "2000", "--frames", "700", "--out", str(tmp_path)])
    assert results["exported filter"] < 0.7 * results["integrator"]
    printed = capsys.readouterr().out
    assert "identified DM gain" in printed and "exported filter: median residual RMS" in printed
    with fits.open(tmp_path / "filter.fits") as hdul:
        assert hdul[0].header["HISTKIND"] == "open_loop" and abs(hdul[0].header["DMGAIN"] - 1.5) < 0.03
    # Step 3 alone, from the exported file.
    again = example.main(["--n-across", "8", "--train-frames", "2000", "--frames", "700",
                          "--filter", str(tmp_path / "filter.fits"), "--out", str(tmp_path / "again")])
    assert again["exported filter"] < 0.7 * again["integrator"]
