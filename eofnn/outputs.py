"""One policy for everything eofnn writes: never replace a user's file unasked, never leave a half-written one.

Outputs are checked before any work starts (exists? writable?), then written into a temporary sibling and moved
into place only when complete, so an interrupted or crashed run leaves either the old result or the new one:

- Ctrl-C and SIGTERM remove the staged sibling (:mod:`eofnn.cli.signals` turns SIGTERM into an interruption).
- SIGKILL cannot be handled: the final move is one atomic system call (``renameat2(RENAME_EXCHANGE)`` for a folder
  over an earlier one, ``rename`` otherwise), and what a killed run left (``.NAME.partial-PID``, ``.NAME.old-PID``) is
  removed by the next run into the same folder once no process holds it (:func:`clean_stale_staging`).
- A full disk is one line (:class:`~eofnn.errors.OutputError`) naming the output and the space left; the staged
  sibling is removed.
- One run at a time per output: :func:`claim_output` holds an exclusive ``flock`` on the hidden ``.NAME.lock``
  beside it while the run writes (the kernel releases it when the process ends, however it ends); a second run
  into the same output is refused in one line.
"""

from __future__ import annotations

import ctypes
import errno
import os
import re
import shutil
import signal
import tempfile
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from eofnn.errors import ConfigError, OutputBusyError, OutputError, OutputExistsError

try:
    import fcntl
except ImportError:  # Windows: no flock; outputs are still staged, only concurrent runs are not refused
    fcntl = None


def _writable_parent(path: Path, what: str) -> None:
    """The nearest existing ancestor of ``path`` must be a writable folder."""
    parent = path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"{what}={str(path)!r} cannot be written: {str(parent)!r} is a file, not a folder")
    try:  # a real write, not os.access: root passes that test even on read-only file systems
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as err:
        raise ConfigError(f"{what}={str(path)!r} cannot be written: folder {str(parent)!r} is not writable "
                          f"({err.strerror or type(err).__name__})") from None


def check_output_file(path: str | Path, overwrite: bool, what: str = "out") -> Path:
    """Refuse an existing file (unless ``overwrite``), a folder in its place, or a place that cannot be written."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{what}={str(path)!r} is a folder: give a file name")
    if path.exists() and not overwrite:
        raise OutputExistsError(f"{str(path)!r} exists: choose another --out or pass --overwrite true")
    _writable_parent(path, what)
    return path


def check_output_folder(path: str | Path, overwrite: bool, what: str = "out") -> Path:
    """Refuse a non-empty folder (unless ``overwrite``), a file in its place, or a place that cannot be written."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{what}={str(path)!r} is a file, not a folder")
    if path.exists() and any(path.iterdir()) and not overwrite:
        raise OutputExistsError(f"{what}={str(path)!r} is not empty: choose another folder or pass --overwrite true")
    _writable_parent(path, what)
    return path


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT/SIGTERM for the few system calls that swap a result into place."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _partial_name(path: Path, tag: str) -> Path:
    return path.with_name(f".{path.name}.{tag}-{os.getpid()}")


#: What eofnn stages beside an output ``NAME``: ``.NAME.partial-PID`` (a folder, or a file of ``write_text_atomic``),
#: ``.STEM.partial-PID.SUFFIX`` (a file of :func:`staged_file`) and ``.NAME.old-PID`` (an earlier folder moved aside).
_STAGED = re.compile(r"^\.(?P<stem>.+)\.(?P<tag>partial|old)-(?P<pid>[0-9]+)(?P<suffix>\.[A-Za-z0-9]+)?$")
#: The lock file of an output ``NAME`` (:func:`claim_output`).
_LOCK = re.compile(r"^\.(?P<name>.+)\.lock$")
#: errno values that mean the output's file system is full (ENOSPC) or the user's quota is spent (EDQUOT).
DISK_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}


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


def _staged_bytes(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


def _size(n: float) -> str:
    for unit in ("bytes", "kB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n} TB"  # unreachable


def _disk_full(err: OSError, path: Path, staged: Path, what: str) -> OutputError:
    """The one line for a full disk (or spent quota) while ``staged`` was being written for ``path``."""
    try:
        wrote = _staged_bytes(staged) if staged.exists() else 0
    except OSError:
        wrote = 0
    try:
        free = f"{_size(shutil.disk_usage(path.parent).free)} free there now"
    except OSError:
        free = "free space unknown"
    reason = "no space left on device" if err.errno == errno.ENOSPC else "disk quota exceeded"
    return OutputError(f"{what}={str(path)!r}: {reason} while writing {str(err.filename or staged)!r} "
                       f"({_size(wrote)} written, {free}): nothing was written, any earlier result is untouched")


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap ``a`` and ``b`` in one system call (Linux ``renameat2(RENAME_EXCHANGE)``): a process killed at any
    moment leaves both names in place. False where the system or file system cannot (then nothing moved)."""
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, getattr(errno, "ENOTSUP", errno.EOPNOTSUPP)):
        return False
    raise OSError(code, os.strerror(code), str(a), None, str(b))


def _move_into_place(partial: Path, path: Path) -> None:
    """Put the complete folder ``partial`` at ``path`` in one atomic step; an earlier ``path`` is then removed."""
    with _signals_deferred():
        if not path.exists():
            os.replace(partial, path)
            return
        if _exchange(partial, path):
            old = partial  # the earlier result now lies at the staged name
        else:  # two renames; a kill between them leaves .NAME.old-PID, put back by clean_stale_staging
            old = _partial_name(path, "old")
            os.replace(path, old)
            os.replace(partial, path)
    shutil.rmtree(old, ignore_errors=True)


#: The list of the files eofnn wrote into an output folder, so that ``--overwrite`` replaces only those.
MANIFEST = ".eofnn-outputs"


def _files(folder: Path) -> list[Path]:
    return sorted(p.relative_to(folder) for p in folder.rglob("*") if p.is_file() or p.is_symlink())


def _written_before(folder: Path) -> set[Path] | None:
    try:
        return {Path(line) for line in (folder / MANIFEST).read_text().splitlines() if line}
    except OSError:
        return None


def _keep_foreign_files(old: Path, new: Path) -> list[str]:
    """Copy into ``new`` every file of ``old`` that eofnn did not write (per ``old``'s manifest; without one, every
    file whose name the new output does not use), so replacing ``old`` deletes nothing of the user's."""
    written = _written_before(old)
    kept = []
    for rel in _files(old):
        if rel == Path(MANIFEST) or (written is not None and rel in written):
            continue
        target = new / rel
        if target.exists() or target.is_symlink():
            if written is None:
                continue  # a name the new output writes: an earlier output of eofnn (written before manifests)
            target = target.with_name(target.name + ".yours")  # the user's file under an output's name: keep both
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(old / rel, target, follow_symlinks=False)
        kept.append(str(rel))
    return kept


@contextmanager
def staged_folder(path: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; on success it replaces ``path``, on failure it is removed.

    Only what eofnn wrote is replaced: files a user put into an earlier output folder are carried over (copied
    before the swap, so an interruption loses nothing) and named in a warning; the new folder lists its own files
    in :data:`MANIFEST`. ``path`` is claimed for the whole block (:func:`claim_output`), what killed runs left beside
    it is cleaned first (:func:`clean_stale_staging`), and a full disk is one :class:`OutputError` line.
    """
    path = check_output_folder(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    with claim_output(path):
        clean_stale_staging(path.parent)
        partial = _partial_name(path, "partial")
        try:
            shutil.rmtree(partial, ignore_errors=True)
            partial.mkdir()
            yield partial
            (partial / MANIFEST).write_text("".join(f"{rel}\n" for rel in _files(partial)))
            kept = _keep_foreign_files(path, partial) if path.is_dir() else []
            if kept:
                warnings.warn(f"kept {len(kept)} file(s) in {str(path)!r} that eofnn did not write: "
                              f"{', '.join(kept[:5])}{' ...' if len(kept) > 5 else ''}", stacklevel=3)
            _move_into_place(partial, path)
        except OSError as err:
            if err.errno not in DISK_FULL:
                shutil.rmtree(partial, ignore_errors=True)
                raise
            message = _disk_full(err, path, partial, "out")
            shutil.rmtree(partial, ignore_errors=True)
            raise message from None
        except BaseException:
            shutil.rmtree(partial, ignore_errors=True)
            raise


@contextmanager
def staged_file(path: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary file name beside ``path`` (same suffix); on success it replaces ``path`` atomically.

    As :func:`staged_folder`: ``path`` is claimed, stale staging beside it cleaned, a full disk one line."""
    path = check_output_file(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    with claim_output(path):
        clean_stale_staging(path.parent)
        partial = path.with_name(f".{path.stem}.partial-{os.getpid()}{path.suffix}")
        with _partial_removed_on_failure(partial, path, "out"):
            yield partial
            with _signals_deferred():
                os.replace(partial, path)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file, flushed to disk before it replaces ``path``, so a reader
    (or a crash) sees the old file or the new one, never half of it; on any failure the temporary file is removed
    (a full disk: one :class:`OutputError` line)."""
    path = Path(path)
    partial = path.with_name(f".{path.name}.partial-{os.getpid()}")
    with _partial_removed_on_failure(partial, path, "file"):
        with open(partial, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(partial, path)


@contextmanager
def _partial_removed_on_failure(partial: Path, path: Path, kind: str) -> Iterator[None]:
    """On any failure inside the block the staged file ``partial`` (of ``path``) is removed; a full disk becomes one
    :class:`OutputError` line."""
    try:
        yield
    except OSError as err:
        if err.errno not in DISK_FULL:
            partial.unlink(missing_ok=True)
            raise
        message = _disk_full(err, path, partial, kind)
        partial.unlink(missing_ok=True)
        raise message from None
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
