"""An interrupted run loses nothing: Ctrl-C (a real SIGINT) or SIGTERM during ``compare --overwrite true`` over a complete
earlier result leaves that result exactly as it was, SIGKILL too (and the next run removes what the killed one left),
and a finished run replaces it whole, never a mix of the two. Other faults (a full disk, two runs into one output, a
telemetry file that changes): tests/test_faults.py."""

from __future__ import annotations

import os
import select
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


def _well_under_way(proc: subprocess.Popen, tmp_path: Path) -> None:
    """Wait until the run is well under way: its staging folder holds a trained checkpoint."""
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if list(tmp_path.glob(".run.partial-*/checkpoints/*.ckpt")):
            break
        time.sleep(0.2)
    assert proc.poll() is None, "the run ended before it could be interrupted"


@pytest.mark.parametrize(("sent", "status", "said"), [(signal.SIGINT, 130, "eofnn: interrupted"),
                                                      (signal.SIGTERM, 143, "eofnn: terminated (SIGTERM)")],
                         ids=["ctrl_c", "sigterm"])
def test_ctrl_c_or_sigterm_during_an_overwrite_leaves_the_earlier_result(tmp_path, sent, status, said):
    """SIGTERM (timeout, batch schedulers, Ray) is handled as Ctrl-C, with its own exit status (128 + 15)."""
    out = tmp_path / "run"
    before = _earlier_result(out)
    proc = _compare(out)
    _well_under_way(proc, tmp_path)
    proc.send_signal(sent)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == status, err
    lines = [line for line in err.strip().splitlines() if line.startswith("eofnn:")]
    assert lines[-1].startswith(said) and "Traceback" not in err
    assert _contents(out) == before and sorted(p.name for p in out.iterdir()) == sorted(before)
    assert not list(tmp_path.glob(".run.*")), "no staging folder is left behind"


def test_sigkill_during_an_overwrite_leaves_the_earlier_result_and_the_next_run_cleans_up(tmp_path):
    """SIGKILL cannot be handled: the earlier result stays (the new one is moved in by one atomic step, never reached
    here), and the next run into the same folder removes the killed run's staging and lock file."""
    out = tmp_path / "run"
    before = _earlier_result(out)
    proc = _compare(out)
    _well_under_way(proc, tmp_path)
    proc.kill()
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    assert _contents(out) == before and sorted(p.name for p in out.iterdir()) == sorted(before)
    assert [p.name for p in tmp_path.glob(".run.partial-*")] == [f".run.partial-{proc.pid}"]
    following = subprocess.run([sys.executable, "-m", "eofnn.cli.main", "simulate", "--scenario",
                                str(CONF / "tiny_scenario.yaml"), "--frames", "20", "--out", str(tmp_path / "next.npz")],
                               capture_output=True, text=True, timeout=300)
    assert following.returncode == 0, following.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["next.npz", "next.npz.png", "run"]
    assert _contents(out) == before


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


#: The child of the test below: the console script, held inside its import of eofnn.cli.main (at the first module that
#: import looks for, eofnn.cli.commands today) until the test has sent its signal. It says so on stdout, then waits on
#: stdin, which the test closes only after signalling: the signal cannot come before console() answers signals (a
#: traceback from Python's start) nor after the import is done (main() answering instead), and the run cannot go on
#: to finish first (exit status 0).
_HELD_IN_THE_IMPORT = """\
import os, sys
from importlib.abc import MetaPathFinder

class Hold(MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if "eofnn.cli.main" in sys.modules and name != "eofnn.cli.main":
            sys.meta_path.remove(self)
            print(f"held importing {name} for eofnn.cli.main", flush=True)
            os.read(0, 1)  # returns when the test closes stdin; the signal ends the wait first, with its exception
        return None

sys.argv = ["eofnn", "compare", "--config", sys.argv[1], "--out", sys.argv[2]]
from eofnn.cli.console import console
sys.meta_path.insert(0, Hold())
console()
"""


@pytest.mark.parametrize(("sent", "status", "said"), [(signal.SIGINT, 130, "eofnn: interrupted"),
                                                      (signal.SIGTERM, 143, "eofnn: terminated (SIGTERM)")],
                         ids=["ctrl_c", "sigterm"])
def test_ctrl_c_or_sigterm_while_eofnn_is_still_importing_is_one_line(tmp_path, sent, status, said):
    """The console script answers Ctrl-C and SIGTERM even during its imports (torch, Lightning: seconds), without a
    traceback. The signal is sent while the child is held inside the import (:data:`_HELD_IN_THE_IMPORT`), not after
    a guessed delay."""
    proc = subprocess.Popen([sys.executable, "-c", _HELD_IN_THE_IMPORT, str(CONF / "tiny_compare.yaml"),
                             str(tmp_path / "out")], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_sigint_default)
    try:
        assert select.select([proc.stdout], [], [], 300)[0], "the child never reached the import of eofnn.cli.main"
        held = proc.stdout.readline()
        assert held.startswith("held importing ") and held.rstrip().endswith(" for eofnn.cli.main"), held
        proc.send_signal(sent)
        out, err = proc.communicate(timeout=120)  # closes stdin: a child the signal did not end would run on
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == status, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith(said)
    assert not out and not (tmp_path / "out").exists()
