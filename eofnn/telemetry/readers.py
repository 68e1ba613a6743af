"""Where the big arrays of a telemetry file lie on disk, and reading blocks of their frames (no memory map).

- :class:`RawReader`: an array stored contiguously (FITS image data, an npz member stored uncompressed): one
  ``seek`` and ``readinto`` per block, into a buffer of the file's own dtype.
- :class:`ZipReader`: a compressed npz member, decompressed forward.

:func:`npz_readers` and :func:`fits_readers` locate ``y``, ``wfs`` and ``slopes`` (:data:`STREAMED`) from the
headers alone; :mod:`eofnn.telemetry.file` builds lazy frame arrays on them.

A file is read over minutes (passes of a fit, an identification): each reader keeps the file's identity, size and
modification time when it was located (:class:`FileState`) and compares them after every block, so a file that is
truncated, rewritten or replaced while it is read is one :class:`TelemetryError` line saying what changed, never a
traceback or blocks of two different files.
"""

from __future__ import annotations

import os
import struct
import time
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np

from eofnn.errors import TelemetryError

#: Arrays read in blocks (the others are small and read whole).
STREAMED = ("y", "wfs", "slopes")
_FITS_DTYPES = {-32: ">f4", -64: ">f8", 8: "u1", 16: ">i2", 32: ">i4", 64: ">i8"}


class FileState(NamedTuple):
    """What identifies the contents of a file without reading it: device and inode (replaced?), size (truncated,
    appended?) and modification time in nanoseconds (rewritten in place?)."""

    device: int
    inode: int
    size: int
    mtime_ns: int

    @classmethod
    def of(cls, stat: os.stat_result) -> FileState:
        return cls(stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns)


def file_state(path: Path) -> FileState:
    """The :class:`FileState` of ``path`` now."""
    return FileState.of(os.stat(path))


def _when(ns: int) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(ns / 1e9)) + f".{ns % 1_000_000_000 // 1_000_000:03d}"


def changed_error(path: Path, name: str, at_open: FileState, now: FileState | None,
                  doing: str) -> TelemetryError | None:
    """The one line for a file that is no longer what it was when opened (``now``: None when it is gone), or None."""
    if now == at_open:
        return None
    if now is None:
        what = "it was removed"
    else:
        changes = []
        if (now.device, now.inode) != (at_open.device, at_open.inode):
            changes.append("it was replaced by another file")
        if now.size != at_open.size:
            changes.append(f"size {at_open.size} -> {now.size} bytes")
        if now.mtime_ns != at_open.mtime_ns:
            changes.append(f"modified {_when(at_open.mtime_ns)} -> {_when(now.mtime_ns)}")
        what = ", ".join(changes)
    return TelemetryError(f"telemetry file {str(path)!r} changed while it was read ({what}; array {name!r}, "
                          f"{doing}): stream a finished file (copy it once its writer is done)")


class NotStreamableError(TelemetryError):
    """The file is valid telemetry but its frames are not contiguous on disk (Fortran order, a compressed or BLANK
    image): it can be read whole (:meth:`Telemetry.load`), not in blocks."""


class RawReader:
    """One array stored contiguously (C order) at ``offset`` bytes of ``path``: blocks by ``seek`` + ``readinto``."""

    def __init__(self, path: Path, name: str, offset: int, dtype: np.dtype, shape: tuple[int, ...],
                 scale: tuple[float, float] | None = None, state: FileState | None = None) -> None:
        self.path, self.name, self.offset, self.dtype, self.shape, self.scale = path, name, offset, dtype, shape, scale
        #: The file as it was when located; every block is checked against it (module docstring).
        self.state = file_state(path) if state is None else state

    def read(self, batch: int, start: int, stop: int) -> np.ndarray:
        frames, width = self.shape[-2:]
        out = np.empty((stop - start, width), dtype=self.dtype)
        doing = f"frames {start} .. {stop - 1} of recording {batch}"
        try:
            f = open(self.path, "rb", buffering=0)
        except FileNotFoundError:
            raise changed_error(self.path, self.name, self.state, None, doing) from None
        with f:
            f.seek(self.offset + (batch * frames + start) * width * self.dtype.itemsize)
            view, got = out.reshape(-1).view(np.uint8), 0
            while got < view.size:  # readinto may return less than asked (large reads, pipes)
                n = f.readinto(view[got:])
                if not n:
                    break
                got += n
            # After the read: a change before or during it shows here (the block would mix two files' bytes).
            changed = changed_error(self.path, self.name, self.state, FileState.of(os.fstat(f.fileno())), doing)
        if changed is not None:
            raise changed
        if got < view.size:
            raise TelemetryError(f"telemetry file {str(self.path)!r} is truncated: array {self.name!r} "
                                 f"ends before frame {stop} of recording {batch} (short read: {got} of {view.size} "
                                 "bytes)")
        return out


class ZipReader:
    """A compressed npz member: decompressed forward; the last block is kept, so overlapping windows that move
    forward never reopen the member (a new pass does)."""

    def __init__(self, path: Path, name: str, member: str, header: int, dtype: np.dtype, shape: tuple[int, ...],
                 state: FileState | None = None):
        self.path, self.name, self.member, self.header, self.dtype, self.shape = path, name, member, header, dtype, shape
        self.scale = None
        #: The file as it was when located; every block is checked against it (module docstring).
        self.state = file_state(path) if state is None else state
        self._zip = self._stream = None
        self._pos = 0  # bytes of array data consumed from the stream
        self._last: tuple[int, np.ndarray] | None = None  # (first byte, bytes) of the previous block

    def _reopen(self) -> None:
        self.close()
        try:
            self._zip = zipfile.ZipFile(self.path)
        except FileNotFoundError:
            self._zip = None
            raise
        self._stream = self._zip.open(self.member)
        self._stream.read(self.header)
        self._pos = 0

    def _now(self) -> FileState | None:
        try:
            return FileState.of(os.fstat(self._zip.fp.fileno())) if self._zip is not None else file_state(self.path)
        except (OSError, AttributeError, ValueError):
            try:
                return file_state(self.path)
            except OSError:
                return None

    def read(self, batch: int, start: int, stop: int) -> np.ndarray:
        """Frames ``start .. stop - 1`` of recording ``batch``; a change of the file (before or during the read) or
        a member that ends early is one :class:`TelemetryError` line."""
        doing = f"frames {start} .. {stop - 1} of recording {batch}"
        try:
            out = self._read(batch, start, stop)
        except TelemetryError:
            changed = changed_error(self.path, self.name, self.state, self._now(), doing)
            if changed is not None:
                self.close()
                raise changed from None
            raise
        except (OSError, EOFError, zlib.error, zipfile.BadZipFile, struct.error, ValueError) as err:
            changed = changed_error(self.path, self.name, self.state, self._now(), doing)
            self.close()
            if changed is not None:
                raise changed from None
            raise TelemetryError(f"telemetry file {str(self.path)!r} is corrupt: array {self.name!r}, {doing} "
                                 f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})") from None
        changed = changed_error(self.path, self.name, self.state, self._now(), doing)
        if changed is not None:
            self.close()
            raise changed
        return out

    def _read(self, batch: int, start: int, stop: int) -> np.ndarray:
        frames, width = self.shape[-2:]
        size = width * self.dtype.itemsize
        first, n = (batch * frames + start) * size, (stop - start) * size
        out = np.empty((stop - start, width), dtype=self.dtype)
        view, got = out.reshape(-1).view(np.uint8), 0
        if self._last is not None and self._last[0] <= first < self._last[0] + self._last[1].size:
            kept = self._last[1][first - self._last[0]:][:n]
            view[: kept.size] = kept
            got = kept.size
        if got < n:
            if self._stream is None or first + got < self._pos:
                self._reopen()
            while self._pos < first + got:  # skip forward (another recording, or a window past the last block)
                skipped = len(self._stream.read(min(first + got - self._pos, 1 << 24)))
                if not skipped:
                    break
                self._pos += skipped
            while got < n:
                chunk = self._stream.read(n - got)
                if not chunk:
                    raise TelemetryError(f"telemetry file {str(self.path)!r} is truncated: array {self.name!r} "
                                         f"ends before frame {stop} of recording {batch}")
                view[got: got + len(chunk)] = np.frombuffer(chunk, np.uint8)
                got += len(chunk)
                self._pos += len(chunk)
            self._last = (first, view)  # ends where the stream stands: the next window continues from it
        return out

    def close(self) -> None:
        if self._stream is not None:
            self._stream.close()
            self._zip.close()
        self._zip = self._stream = None
        self._last = None

    def __getstate__(self) -> dict:  # DataLoader workers: each opens its own stream
        return {**self.__dict__, "_zip": None, "_stream": None, "_pos": 0, "_last": None}


def npz_readers(path: Path) -> dict:
    """Readers of the streamed arrays of an npz file (name -> :class:`RawReader` or :class:`ZipReader`)."""
    readers = {}
    state = file_state(path)
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if name not in STREAMED:
                continue
            with archive.open(info) as member:
                version = np.lib.format.read_magic(member)
                shape, fortran, dtype = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                         else np.lib.format.read_array_header_2_0)(member)
                header = member.tell()
            _check_stored(path, name, dtype, shape, fortran)
            if info.compress_type == zipfile.ZIP_STORED:
                with open(path, "rb") as f:  # the member's data follow its local header, name and extra field
                    f.seek(info.header_offset)
                    local = f.read(30)
                    if len(local) < 30 or local[:4] != b"PK\x03\x04":
                        raise TelemetryError(f"telemetry file {str(path)!r} is corrupt (member {info.filename})")
                    name_len, extra_len = struct.unpack("<HH", local[26:30])
                offset = info.header_offset + 30 + name_len + extra_len + header
                reader = RawReader(path, name, offset, dtype, shape, state=state)
                if offset + dtype.itemsize * int(np.prod(shape)) > state.size:
                    raise TelemetryError(f"telemetry file {str(path)!r} is truncated: array {name!r} {shape} ends "
                                         "past the end of the file")
            else:
                reader = ZipReader(path, name, info.filename, header, dtype, shape, state)
            readers[name] = reader
    return readers


def fits_readers(path: Path) -> dict:
    from astropy.io import fits

    """Readers of the streamed arrays of a FITS file (name -> :class:`RawReader`)."""
    readers = {}
    state = file_state(path)
    size = state.size
    with warnings.catch_warnings(record=True) as caught, fits.open(path, memmap=False) as hdul:
        warnings.simplefilter("always")
        for index, hdu in enumerate(hdul):
            name = hdu.name.lower()
            if name not in STREAMED or hdu.header.get("NAXIS", 0) == 0:
                continue
            if not isinstance(hdu, fits.ImageHDU) or hdu.header.get("ZIMAGE") or "BLANK" in hdu.header:
                raise NotStreamableError(f"telemetry file {str(path)!r}: HDU {hdu.name} is a {type(hdu).__name__}: "
                                     "streamed reading needs an uncompressed image without BLANK values")
            header = hdu.header
            bitpix = header["BITPIX"]
            if bitpix not in _FITS_DTYPES:
                raise TelemetryError(f"telemetry file {str(path)!r}: HDU {hdu.name} has BITPIX={bitpix}: allowed "
                                     f"are {sorted(_FITS_DTYPES)}")
            dtype = np.dtype(_FITS_DTYPES[bitpix])
            shape = tuple(int(header[f"NAXIS{k}"]) for k in range(header["NAXIS"], 0, -1))
            _check_stored(path, name, dtype, shape, False)
            offset = hdul.fileinfo(index)["datLoc"]
            if offset + dtype.itemsize * int(np.prod(shape)) > size:
                raise TelemetryError(f"telemetry file {str(path)!r} is truncated: array {name!r} {shape} ends past "
                                     "the end of the file")
            scale = (float(header.get("BSCALE", 1.0)), float(header.get("BZERO", 0.0)))
            readers[name] = RawReader(path, name, offset, dtype, shape, None if scale == (1.0, 0.0) else scale, state)
    problems = [str(w.message).splitlines()[0] for w in caught if "astropy" in type(w.message).__module__]
    if problems:
        raise TelemetryError(f"telemetry file {str(path)!r} is truncated or corrupt ({problems[0]})")
    return readers


def _check_stored(path: Path, name: str, dtype: np.dtype, shape: tuple, fortran: bool) -> None:
    if dtype.kind not in "fiu":
        raise TelemetryError(f"telemetry array {name!r} has dtype {dtype}: it must hold real numbers (nm)")
    if len(shape) not in (2, 3):
        raise TelemetryError(f"telemetry array {name!r} has shape {shape}: expected (frames, actuators) or "
                             "(batch, frames, actuators)")
    if fortran and shape[-2] > 1 and shape[-1] > 1:
        raise NotStreamableError(f"telemetry file {str(path)!r}: array {name!r} is stored in Fortran order, so its "
                             "frames are not contiguous on disk: save np.ascontiguousarray(...) to stream it, or read "
                             "it whole (Telemetry.load)")
