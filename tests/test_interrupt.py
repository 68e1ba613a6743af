"""An interrupted run loses nothing: Ctrl-C (a real SIGINT) during ``compare --overwrite true`` over a complete earlier
result leaves that result exactly as it was, and a finished run replaces it whole, never a mix of the two."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.cli, pytest.mark.slow]

CONF = Path(__file__).parent / "conf"


def _sigint_default() -> None:
    """In the child: Ctrl-C's default disposition, even when the test runner ignores SIGINT (``nohup``, a
    background job), so that Python installs its KeyboardInterrupt handler as it does for a user."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _earlier_result(folder: Path) -> dict[str, bytes]:
    folder.mkdir()
    files = {"metrics.json": b'{"scenarios": "the earlier result"}', "config.yaml": b"earlier: true\n",
             "results.md": b"# earlier\n"}
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return files


def _contents(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def _compare(out: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "eofnn.cli.main", "compare", "--config", str(CONF / "tiny_compare.yaml"),
                             "--out", str(out), "--overwrite", "true"], stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=_sigint_default)


def test_ctrl_c_during_an_overwrite_leaves_the_earlier_result(tmp_path):
    out = tmp_path / "run"
    before = _earlier_result(out)
    proc = _compare(out)
    deadline = time.monotonic() + 300
    # Wait until the run is well under way: its staging folder holds a trained checkpoint.
    while time.monotonic() < deadline and proc.poll() is None:
        if list(tmp_path.glob(".run.partial-*/checkpoints/*.ckpt")):
            break
        time.sleep(0.2)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    lines = [line for line in err.strip().splitlines() if line.startswith("eofnn:")]
    assert lines[-1].startswith("eofnn: interrupted") and "Traceback" not in err
    assert _contents(out) == before and sorted(p.name for p in out.iterdir()) == sorted(before)
    assert not list(tmp_path.glob(".run.*")), "no staging folder is left behind"


def test_a_finished_overwrite_replaces_the_result_whole(tmp_path):
    out = tmp_path / "run"
    _earlier_result(out)
    proc = _compare(out)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    after = _contents(out)
    assert b"the earlier result" not in after["metrics.json"] and b"earlier" not in after["results.md"]
    assert {"metrics.json", "results.md", "config.yaml", "rms_vs_time.png", "residual_psd.png"} <= set(after)
    assert (out / "checkpoints").is_dir() and not list(tmp_path.glob(".run.*"))


def test_ctrl_c_while_eofnn_is_still_importing_is_one_line_and_130(tmp_path):
    """The console script answers Ctrl-C even during its imports (torch, Lightning: seconds), without a traceback."""
    code = ("import sys; sys.argv = ['eofnn', 'compare', '--config', sys.argv[1], '--out', sys.argv[2]];"
            "from eofnn.cli.console import console; console()")
    proc = subprocess.Popen([sys.executable, "-c", code, str(CONF / "tiny_compare.yaml"), str(tmp_path / "out")],
                            stderr=subprocess.PIPE, text=True, preexec_fn=_sigint_default)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("eofnn: interrupted")
    assert not (tmp_path / "out").exists()
