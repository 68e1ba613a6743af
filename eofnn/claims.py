"""One eofnn run at a time per output, and the clean-up of what killed runs left beside outputs.

:func:`claim_output` holds an exclusive ``flock`` on the hidden ``.NAME.lock`` beside an output ``NAME`` while a run
writes it (the kernel releases it when the process ends, however it ends); a second run into the same output is
refused in one line. :func:`clean_stale_staging` removes what runs killed by SIGKILL left (``.NAME.partial-PID``,
``.NAME.old-PID``, lock files), only once their process is gone and no one holds the output. The staged writes
themselves are :mod:`eofnn.outputs`.
"""

from __future__ import annotations

import os
import re
import shutil
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from eofnn.errors import OutputBusyError

try:
    import fcntl
except ImportError:  # Windows: no flock; outputs are still staged, only concurrent runs are not refused
    fcntl = None

#: What eofnn stages beside an output ``NAME``: ``.NAME.partial-PID`` (a folder, or a file of ``write_text_atomic``),
#: ``.STEM.partial-PID.SUFFIX`` (a file of :func:`staged_file`) and ``.NAME.old-PID`` (an earlier folder moved aside).
_STAGED = re.compile(r"^\.(?P<stem>.+)\.(?P<tag>partial|old)-(?P<pid>[0-9]+)(?P<suffix>\.[A-Za-z0-9]+)?$")
#: The lock file of an output ``NAME`` (:func:`claim_output`).
_LOCK = re.compile(r"^\.(?P<name>.+)\.lock$")


def _process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (a process of another user counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class _OutputLock:
    """An exclusive ``flock`` on ``.NAME.lock`` beside the output ``NAME``; the file holds the owner's process id.

    The lock file is removed on release while still locked; a process that opened it just before then finds, once
    it holds the lock, that the file at that name is no longer the one it locked, and tries again.
    """

    def __init__(self, path: Path) -> None:
        self.path, self.file = path, path.with_name(f".{path.name}.lock")
        self._fd: int | None = None

    def acquire(self) -> bool:
        """Take the lock without waiting; False when another process (or another claim of this one) holds it."""
        if fcntl is None:
            return True
        while True:
            try:
                fd = os.open(self.file, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError:
                return True  # an unwritable folder: the output checks refuse it in their own line
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                return False
            except OSError as err:  # a file system without locks (some network mounts): staged writes still hold
                os.close(fd)
                warnings.warn(f"cannot lock {str(self.file)!r} ({err.strerror}): a second run into "
                              f"{str(self.path)!r} at the same time would not be refused", stacklevel=4)
                return True
            try:
                current = os.stat(self.file).st_ino
            except FileNotFoundError:
                current = None
            if current == os.fstat(fd).st_ino:
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
                self._fd = fd
                return True
            os.close(fd)  # locked a file its last holder had just removed: lock the one at that name now

    def holder(self) -> str:
        """The process id written by the holder, or ``'?'``."""
        try:
            return self.file.read_text().strip() or "?"
        except OSError:
            return "?"

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            self.file.unlink(missing_ok=True)
        except OSError:
            pass
        os.close(self._fd)  # closing the last descriptor releases the flock
        self._fd = None


#: Outputs this process has claimed (path -> [lock, depth]): a claim inside a claim of the same output is free.
_CLAIMED: dict[Path, list] = {}


@contextmanager
def claim_output(path: str | Path, what: str = "out") -> Iterator[None]:
    """Hold ``path`` for this process while the block runs: refused with one :class:`OutputBusyError` line while
    another eofnn process writes there; released on exit, and by the kernel if the process is killed.

    A command claims its output when it starts (so a second run is refused before it works), and
    :func:`staged_folder` and :func:`staged_file` claim it again (free: claims nest within a process).
    """
    key = Path(os.path.abspath(path))
    if key not in _CLAIMED and not key.parent.is_dir():
        yield  # no folder yet, so nothing to protect yet: staged_folder/staged_file claim it once they make it
        return
    if key in _CLAIMED:
        _CLAIMED[key][1] += 1
        try:
            yield
        finally:
            _CLAIMED[key][1] -= 1
        return
    lock = _OutputLock(key)
    if not lock.acquire():
        raise OutputBusyError(f"{what}={str(path)!r} is being written by another eofnn run (process {lock.holder()}, "
                              f"lock {str(lock.file)!r}): wait for it to finish or choose another {what}")
    _CLAIMED[key] = [lock, 1]
    try:
        yield
    finally:
        _CLAIMED[key][1] -= 1
        if _CLAIMED[key][1] == 0:
            del _CLAIMED[key]
            lock.release()


def _remove(entry: Path) -> None:
    if entry.is_dir() and not entry.is_symlink():
        shutil.rmtree(entry, ignore_errors=True)
    else:
        entry.unlink(missing_ok=True)


def clean_stale_staging(parent: str | Path) -> list[str]:
    """Remove what killed eofnn runs left in ``parent`` (the names of :data:`_STAGED`, and lock files whose
    process is gone); returns their names.

    Only entries whose process is gone and whose output no other process claims (:func:`claim_output`) are touched;
    each is handled under that output's lock. An earlier folder moved aside (``.NAME.old-PID``) by a run killed
    before it moved the new one in is put back as ``NAME`` when nothing is there: the old result, never a mix.
    """
    parent = Path(parent)
    removed: list[str] = []
    try:
        entries = sorted(parent.iterdir())
    except OSError:
        return removed
    for entry in entries:
        lock_of = _LOCK.match(entry.name)
        if lock_of is not None:  # a lock file a killed run left (the kernel released its lock): taken and removed
            key = Path(os.path.abspath(parent / lock_of["name"]))
            holder = _OutputLock(key)
            if key not in _CLAIMED and holder.holder().isdigit() and not _process_alive(int(holder.holder())) \
                    and holder.acquire():
                holder.release()
                removed.append(entry.name)
            continue
        match = _STAGED.match(entry.name)
        if match is None or int(match["pid"]) == os.getpid() or _process_alive(int(match["pid"])):
            continue
        target = parent / (match["stem"] + (match["suffix"] or ""))
        if match["tag"] == "old" and match["suffix"]:
            continue  # not a name eofnn writes
        key = Path(os.path.abspath(target))
        claimed_here = key in _CLAIMED
        lock = _OutputLock(key)
        if not claimed_here and not lock.acquire():
            continue  # a live run writes that output: its own staging is none of ours (pid reuse cannot fool this)
        try:
            if not (entry.exists() or entry.is_symlink()):
                continue
            if match["tag"] == "old" and not (target.exists() or target.is_symlink()):
                os.replace(entry, target)
                warnings.warn(f"restored {str(target)!r} from {entry.name!r}, left by a run killed while it moved "
                              "its result into place", stacklevel=3)
                continue
            _remove(entry)
            removed.append(entry.name)
        finally:
            if not claimed_here:
                lock.release()
    return removed
