"""Faults beyond Ctrl-C: a full disk, a run killed with SIGKILL, two runs into one output, SIGTERM, and a telemetry
file that changes while it is streamed. Each is one line (or nothing at all), and nothing a user wrote is lost or
left half-written (eofnn.outputs, eofnn.telemetry.readers). Real signals to whole runs: tests/test_interrupt.py.
"""

from __future__ import annotations

import errno
import fcntl
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from eofnn import outputs
from eofnn.errors import OutputBusyError, OutputError, TelemetryError
from eofnn.outputs import claim_output, clean_stale_staging, staged_file, staged_folder, write_text_atomic
from eofnn.telemetry.file import StreamedTelemetry
from eofnn.telemetry.record import Telemetry

TINY_SCENARIO = Path(__file__).parent / "conf" / "tiny_scenario.yaml"


def _earlier_result(folder: Path) -> dict[str, bytes]:
    folder.mkdir()
    files = {"metrics.json": b'{"earlier": true}', "results.md": b"# earlier\n",
             outputs.MANIFEST: b"metrics.json\nresults.md\n"}  # all eofnn's: nothing is carried over
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return files


def _contents(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def _dead_pid() -> int:
    """A process id no process has (the leftovers of a killed run carry one): above the largest Linux allows."""
    return 4_194_305


def _hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def _disk_full(*_args, **_kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


# --- a full disk ----------------------------------------------------------------------------------------------------

def test_a_full_disk_in_a_staged_folder_is_one_line_and_keeps_the_earlier_result(tmp_path):
    out = tmp_path / "run"
    before = _earlier_result(out)
    with pytest.raises(OutputError) as caught, staged_folder(out, overwrite=True) as staging:
        (staging / "metrics.json").write_bytes(b"x" * 5000)
        _disk_full()
    message = str(caught.value)
    assert "\n" not in message and str(out) in message and "no space left on device" in message
    assert "5.0 kB written" in message and "free there now" in message and "untouched" in message
    assert _contents(out) == before and _hidden(tmp_path) == []


def test_a_full_disk_while_the_result_moves_into_place_keeps_the_earlier_result(tmp_path, monkeypatch):
    """The disk can fill after the command's last write: copying the user's own files into the new folder."""
    out = tmp_path / "run"
    before = _earlier_result(out)
    (out / "notes.txt").write_text("mine")  # a user's file: copied into the new result before the swap
    before["notes.txt"] = b"mine"
    monkeypatch.setattr(outputs.shutil, "copy2", _disk_full)
    with pytest.raises(OutputError, match="no space left"), staged_folder(out, overwrite=True) as staging:
        (staging / "metrics.json").write_text("{}")
    assert _contents(out) == before and _hidden(tmp_path) == []


def test_a_full_disk_in_a_staged_file_or_an_atomic_text_is_one_line_and_nothing_half_written(tmp_path, monkeypatch):
    target = tmp_path / "run.npz"
    target.write_bytes(b"earlier")
    with pytest.raises(OutputError, match="no space left") as caught, staged_file(target, overwrite=True) as partial:
        partial.write_bytes(b"half")
        _disk_full()
    assert str(target) in str(caught.value) and target.read_bytes() == b"earlier" and _hidden(tmp_path) == []

    real_open = open
    text = tmp_path / "metrics.json"
    text.write_text("earlier")

    class FullFile:
        """A file object whose every write finds the disk full."""

        def __init__(self, path, mode):
            self._f = real_open(path, mode)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._f.close()

        def write(self, _text):
            _disk_full()

    monkeypatch.setattr("builtins.open", lambda path, mode="r", *a, **k: FullFile(path, mode)
                        if ".partial-" in str(path) else real_open(path, mode, *a, **k))
    with pytest.raises(OutputError, match="no space left") as caught:
        write_text_atomic(text, "new")
    assert str(text) in str(caught.value)
    monkeypatch.undo()
    assert text.read_text() == "earlier" and _hidden(tmp_path) == []


@pytest.mark.cli
@pytest.mark.slow
def test_a_full_disk_during_simulate_is_one_line_and_keeps_the_earlier_file(tmp_path, monkeypatch, cli):
    out = tmp_path / "run.npz"
    out.write_bytes(b"the earlier telemetry")

    def half_then_full(self, path, *args, **kwargs):
        Path(path).write_bytes(b"half a file")
        _disk_full()

    monkeypatch.setattr(Telemetry, "save", half_then_full)
    code, err = cli("simulate", "--scenario", TINY_SCENARIO, "--frames", "20", "--out", out, "--overwrite", "true")
    errors = [line for line in err.splitlines() if line.startswith("eofnn: error:")]
    assert code == 2 and len(errors) == 1 and "Traceback" not in err, err
    assert str(out) in errors[0] and "no space left on device" in errors[0] and "free there now" in errors[0]
    assert out.read_bytes() == b"the earlier telemetry" and _hidden(tmp_path) == []


@pytest.mark.cli
def test_a_full_disk_anywhere_else_in_a_command_is_one_line(monkeypatch, cli):
    """A temporary file of a library (not an output eofnn stages) on a full disk: one line too, exit status 2."""
    import eofnn.cli.main

    class FillsTheDisk:
        def run(self):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/tmp/tmpabc123")

    monkeypatch.setattr(eofnn.cli.main, "parse", lambda args: FillsTheDisk())
    code, err = cli("compare", "--config", "any.yaml")
    assert code == 2 and err.strip().splitlines() == [
        "eofnn: error: No space left on device writing '/tmp/tmpabc123': free some space and run again (outputs are "
        "staged: earlier results are untouched)"], err


# --- SIGKILL: an atomic move, and what a killed run left is cleaned ---------------------------------------------------

def test_the_result_is_swapped_in_by_one_atomic_step(tmp_path, monkeypatch):
    """At no moment of the move is the output missing: a SIGKILL there leaves the old result or the new one."""
    out = tmp_path / "run"
    _earlier_result(out)
    renames = []
    real_replace = os.replace

    def watched(src, dst):
        real_replace(src, dst)
        renames.append(out.is_dir())

    monkeypatch.setattr(outputs.os, "replace", watched)
    with staged_folder(out, overwrite=True) as staging:
        (staging / "metrics.json").write_text('{"new": true}')
    assert all(renames), "the output was missing between two renames"
    assert (out / "metrics.json").read_text() == '{"new": true}' and _hidden(tmp_path) == []


def test_the_next_run_removes_what_a_killed_run_left_and_keeps_the_earlier_result(tmp_path):
    out = tmp_path / "run"
    before = _earlier_result(out)
    dead = _dead_pid()
    left = tmp_path / f".run.partial-{dead}"  # a compare killed while it wrote
    (left / "checkpoints").mkdir(parents=True)
    (left / "checkpoints" / "ol.ckpt").write_bytes(b"half")
    (tmp_path / f".run.npz.partial-{dead}").write_bytes(b"half")  # write_text_atomic's, killed
    (tmp_path / f".tel.partial-{dead}.fits").write_bytes(b"half")  # staged_file's, killed
    (tmp_path / ".run.lock").write_text(f"{dead}\n")  # its lock file (the kernel released the lock itself)
    assert _contents(out) == before  # the kill left the earlier result as it was
    with staged_folder(out, overwrite=True) as staging:
        (staging / "metrics.json").write_text('{"new": true}')
    assert (out / "metrics.json").read_text() == '{"new": true}'
    assert _hidden(tmp_path) == []


def test_a_result_moved_aside_by_a_run_killed_mid_move_is_put_back(tmp_path):
    """Where the move takes two renames (no renameat2), a kill between them leaves .NAME.old-PID: restored."""
    dead = _dead_pid()
    aside = tmp_path / f".run.old-{dead}"
    before = _earlier_result(aside)
    (tmp_path / f".run.partial-{dead}").mkdir()
    with pytest.warns(UserWarning, match="restored"):
        clean_stale_staging(tmp_path)
    assert _contents(tmp_path / "run") == before and _hidden(tmp_path) == []


def test_staging_of_a_live_run_or_a_locked_output_is_never_touched(tmp_path):
    live = tmp_path / f".a.partial-{os.getppid()}"  # a process that is alive
    live.mkdir()
    dead = _dead_pid()
    held = tmp_path / f".b.partial-{dead}"  # its process is gone but the output is locked (another machine's run)
    held.mkdir()
    user = tmp_path / ".c.partial-notapid"  # not a name eofnn writes
    user.mkdir()
    fd = os.open(tmp_path / ".b.lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        assert clean_stale_staging(tmp_path) == []
    finally:
        os.close(fd)
    assert live.is_dir() and held.is_dir() and user.is_dir()
    assert clean_stale_staging(tmp_path) == [held.name]
    (tmp_path / ".d.lock").write_text(f"{dead}\n")  # a killed run's lock file, nothing else left
    (tmp_path / ".e.lock").write_text("not a process id\n")  # not eofnn's
    assert clean_stale_staging(tmp_path) == [".d.lock"]
    assert _hidden(tmp_path) == [live.name, ".c.partial-notapid", ".e.lock"]


# --- two runs into one output -----------------------------------------------------------------------------------------

@pytest.mark.cli
def test_a_second_claim_of_a_held_output_is_refused_in_one_line(tmp_path):
    out = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom eofnn.outputs import claim_output\n"
                               "with claim_output(sys.argv[1]):\n    print('held', flush=True)\n    time.sleep(60)\n",
                               str(out)], stdout=subprocess.PIPE, text=True,
                              env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OutputBusyError) as caught, staged_folder(out) as staging:
            (staging / "x").write_text("never")
        message = str(caught.value)
        assert "\n" not in message and str(out) in message and f"process {holder.pid}" in message
        assert not out.exists() and not list(tmp_path.glob(".run.partial-*"))
    finally:
        holder.send_signal(signal.SIGKILL)  # the kernel releases a killed holder's lock
        holder.wait()
    with staged_folder(out) as staging:
        (staging / "x").write_text("written")
    assert (out / "x").read_text() == "written" and _hidden(tmp_path) == []


def test_claims_nest_within_one_process_and_release_on_exit(tmp_path):
    out = tmp_path / "run.npz"
    with claim_output(out):
        assert (tmp_path / ".run.npz.lock").read_text().strip() == str(os.getpid())
        with staged_file(out) as partial:  # the command's own write: the same claim
            partial.write_bytes(b"data")
        fd = os.open(tmp_path / ".run.npz.lock", os.O_RDWR)
        try:
            with pytest.raises(BlockingIOError):
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        finally:
            os.close(fd)
    assert out.read_bytes() == b"data" and _hidden(tmp_path) == []


@pytest.mark.cli
@pytest.mark.slow
def test_simulate_into_an_output_another_run_holds_is_refused_before_it_runs(tmp_path, cli):
    out = tmp_path / "run.npz"
    fd = os.open(tmp_path / ".run.npz.lock", os.O_RDWR | os.O_CREAT)
    os.write(fd, b"4242\n")
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        code, err = cli("simulate", "--scenario", TINY_SCENARIO, "--frames", "20", "--out", out)
    finally:
        os.close(fd)
    assert code == 2 and err.strip().splitlines() == [
        f"eofnn: error: out={str(out)!r} is being written by another eofnn run (process 4242, lock "
        f"{str(tmp_path / '.run.npz.lock')!r}): wait for it to finish or choose another out"], err
    assert not out.exists()


# --- SIGTERM ----------------------------------------------------------------------------------------------------------

@pytest.mark.cli
@pytest.mark.slow
def test_sigterm_in_a_run_is_an_interruption_143_and_keeps_the_earlier_file(tmp_path, monkeypatch, cli):
    out = tmp_path / "run.npz"
    out.write_bytes(b"the earlier telemetry")

    def half_then_terminated(self, path, *args, **kwargs):
        Path(path).write_bytes(b"half a file")
        os.kill(os.getpid(), signal.SIGTERM)  # what timeout, a batch scheduler or Ray sends

    monkeypatch.setattr(Telemetry, "save", half_then_terminated)
    handler = signal.getsignal(signal.SIGTERM)
    code, err = cli("simulate", "--scenario", TINY_SCENARIO, "--frames", "20", "--out", out, "--overwrite", "true")
    assert code == 143 and "Traceback" not in err, err
    assert err.strip().splitlines()[-1] == ("eofnn: terminated (SIGTERM): nothing was written (earlier results are "
                                            "untouched)")
    assert out.read_bytes() == b"the earlier telemetry" and _hidden(tmp_path) == []
    assert signal.getsignal(signal.SIGTERM) == handler  # the caller's handler is back


# --- a telemetry file that changes while it is streamed --------------------------------------------------------------

def _telemetry(path: Path, frames: int = 600, compressed: bool = False, seed: int = 0) -> Path:
    """A small random recording (20 actuators) in ``path`` (.npz or .fits)."""
    rng = np.random.default_rng(seed)
    y, wfs = rng.normal(size=(frames, 20)), rng.normal(size=(frames, 20))
    if compressed:
        np.savez_compressed(path, y=y, wfs=wfs, delay_frames=np.array(2))
        return path
    Telemetry(y=torch.as_tensor(y), wfs=torch.as_tensor(wfs), delay_frames=2).save(path, overwrite=True)
    return path


@pytest.mark.parametrize("suffix", [".npz", ".fits"])
def test_a_telemetry_file_rewritten_between_blocks_is_one_line_not_other_numbers(tmp_path, suffix):
    path = _telemetry(tmp_path / f"t{suffix}")
    streamed = StreamedTelemetry.open(path)
    assert torch.equal(streamed.y[0:200], Telemetry.load(path, required=("y", "wfs")).y[0:200])
    other = _telemetry(tmp_path / f"other{suffix}", seed=1).read_bytes()
    assert len(other) == path.stat().st_size
    with open(path, "r+b") as f:  # another recording of the same shape written over it in place
        f.write(other)
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 1_000_000_000))
    with pytest.raises(TelemetryError) as caught:
        streamed.wfs[400:600]
    message = str(caught.value)
    assert "\n" not in message and str(path) in message and "changed while it was read" in message
    assert "modified" in message and "size" not in message and "'wfs'" in message and "frames 400 .. 599" in message


@pytest.mark.parametrize("compressed", [False, True], ids=["stored", "compressed"])
def test_a_telemetry_file_truncated_between_blocks_is_one_line(tmp_path, compressed):
    path = _telemetry(tmp_path / "t.npz", frames=2000, compressed=compressed)
    size = path.stat().st_size
    streamed = StreamedTelemetry.open(path)
    streamed.wfs[0:100]
    with open(path, "r+b") as f:  # a recorder that starts over, or a copy cut short
        f.truncate(size // 3)
    with pytest.raises(TelemetryError) as caught:
        for a in range(100, 2000, 100):
            streamed.wfs[a: a + 100]
    message = str(caught.value)
    assert "\n" not in message and str(path) in message and "changed while it was read" in message
    assert f"size {size} -> {size // 3} bytes" in message


def test_a_telemetry_file_replaced_or_removed_while_streamed_is_one_line(tmp_path):
    path = _telemetry(tmp_path / "t.npz")
    streamed = StreamedTelemetry.open(path)
    streamed.y[0:100]
    _telemetry(tmp_path / "other.npz", frames=600)
    os.replace(tmp_path / "other.npz", path)  # same size, another file
    with pytest.raises(TelemetryError, match="replaced by another file"):
        streamed.y[100:200]
    path.unlink()
    with pytest.raises(TelemetryError, match="it was removed"):
        streamed.y[100:200]


@pytest.mark.cli
@pytest.mark.slow
def test_identify_on_a_file_truncated_while_it_is_read_is_one_line(tmp_path, monkeypatch, cli):
    from eofnn.telemetry import readers as telemetry_readers

    path = _telemetry(tmp_path / "t.npz", frames=3000)
    real_read = telemetry_readers.RawReader.read
    reads = []

    def truncating(self, batch, start, stop):
        if reads and len(reads) == 1:
            with open(self.path, "r+b") as f:
                f.truncate(self.path.stat().st_size // 2)
        reads.append(start)
        return real_read(self, batch, start, stop)

    monkeypatch.setattr(telemetry_readers.RawReader, "read", truncating)
    code, err = cli("identify", "--telemetry", path, "--out", tmp_path / "plant.json")
    errors = [line for line in err.splitlines() if line.startswith("eofnn: error:")]
    assert code == 2 and len(errors) == 1 and "Traceback" not in err, err
    assert str(path) in errors[0] and "changed while it was read" in errors[0] and "size" in errors[0]
    assert not (tmp_path / "plant.json").exists()
