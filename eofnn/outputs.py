"""One policy for everything eofnn writes: never replace a user's file unasked, never leave a half-written one.

Outputs are checked before any work starts (exists? writable?), then written into a temporary sibling and moved
into place only when complete, so an interrupted or crashed run leaves either the old result or the new one.
"""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from eofnn.errors import ConfigError, OutputExistsError


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
    in :data:`MANIFEST`.
    """
    path = check_output_folder(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = _partial_name(path, "partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    try:
        yield partial
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    (partial / MANIFEST).write_text("".join(f"{rel}\n" for rel in _files(partial)))
    kept = _keep_foreign_files(path, partial) if path.is_dir() else []
    if kept:
        warnings.warn(f"kept {len(kept)} file(s) in {str(path)!r} that eofnn did not write: "
                      f"{', '.join(kept[:5])}{' ...' if len(kept) > 5 else ''}", stacklevel=3)
    old = _partial_name(path, "old")
    with _signals_deferred():
        if path.exists():
            os.replace(path, old)
        os.replace(partial, path)
    shutil.rmtree(old, ignore_errors=True)


@contextmanager
def staged_file(path: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary file name beside ``path`` (same suffix); on success it replaces ``path`` atomically."""
    path = check_output_file(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.stem}.partial-{os.getpid()}{path.suffix}")
    try:
        yield partial
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    with _signals_deferred():
        os.replace(partial, path)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file, flushed to disk before it replaces ``path``, so a reader
    (or a crash) sees the old file or the new one, never half of it."""
    path = Path(path)
    partial = path.with_name(f".{path.name}.partial-{os.getpid()}")
    with open(partial, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(partial, path)
