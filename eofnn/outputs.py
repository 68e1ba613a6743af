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
  into the same output is refused in one line (:mod:`eofnn.claims`, re-exported here).
"""

from __future__ import annotations

import ctypes
import errno
import os
import shutil
import signal
import tempfile
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from eofnn.claims import claim_output, clean_stale_staging
from eofnn.errors import ConfigError, OutputError, OutputExistsError

__all__ = ["DISK_FULL", "MANIFEST", "check_output_file", "check_output_folder", "claim_output", "clean_stale_staging",
           "staged_file", "staged_folder", "write_text_atomic"]


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


#: errno values that mean the output's file system is full (ENOSPC) or the user's quota is spent (EDQUOT).
DISK_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}


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
