"""Telemetry files larger than memory: ``y`` and ``wfs`` read in blocks of frames, never whole.

An ELT-class loop records ~5000 actuators at 1 kHz, 20 MB/s in float32: an hour is 72 GB. :class:`StreamedTelemetry`
reads the header, the small arrays (positions, matrices, modal basis, config) and where each big array lies in the
file; slicing one of its :class:`FrameArray` s (``seq.y[a:b]``) then reads frames ``a .. b-1`` from disk with one
``seek`` and ``readinto`` per array, in the file's own dtype (float32 stays float32 on disk and in the read
buffer), and returns them as float64 (the precision of every computation in eofnn, so a streamed fit equals the
in-memory one to rounding). Nothing maps the whole file: a memory map counts every page it touched as resident.

- FITS: uncompressed image HDUs (``BITPIX`` -32, -64 or integers with ``BSCALE``/``BZERO``), located with
  :meth:`astropy.io.fits.HDUList.fileinfo`.
- npz: members stored as ``np.savez`` writes them are read in place (offset of the ``.npy`` data inside the zip);
  compressed members (``np.savez_compressed``) are decompressed forward, the last block kept for the overlap of
  the next, and reopened only when a pass starts again.

``slopes`` with an interaction matrix or a reconstructor become ``wfs`` block by block
(:func:`eofnn.telemetry.spaces.slopes_reconstructor`). Non-finite values and all-zero recordings are found by
:meth:`StreamedTelemetry.check` (one pass, block by block) before any fit starts.
"""

from __future__ import annotations

import json
import struct
import zipfile
from pathlib import Path

import numpy as np
import torch

from eofnn.errors import TelemetryError
from eofnn.telemetry.readers import STREAMED, NotStreamableError, fits_readers, npz_readers
from eofnn.telemetry.record import TELEMETRY_REQUIRED, Telemetry, _delay, _read_fits, _read_npz, telemetry_path
from eofnn.telemetry.spaces import RCOND, slopes_reconstructor

__all__ = ["FrameArray", "NotStreamableError", "StreamedTelemetry"]

#: Frames per block of :meth:`StreamedTelemetry.check` and :meth:`FrameArray.any` (5 MB of float32 at 5000
#: actuators).
SCAN_FRAMES = 256


class FrameArray:
    """A lazy ``(frames, K)`` (or ``(batch, frames, K)``) array of a telemetry file.

    ``a[i]`` is recording ``i`` of a batched array (lazy); ``a[start:stop]`` of a 2-d one reads those frames and
    returns them as a float64 tensor ``(stop - start, K)``; ``a.narrow(0, start, length)`` is a lazy view.
    ``columns`` (``(S, K)``) maps each block's ``S`` stored columns to the ``K`` returned (``slopes @ R.T``);
    ``factor`` multiplies every block (a record's unit converted to nm, :meth:`scaled`).
    """

    def __init__(self, reader, batch: int | None = None, start: int = 0, frames: int | None = None,
                 columns: torch.Tensor | None = None, factor: float = 1.0) -> None:
        self._reader, self._batch, self._start, self._columns = reader, batch, start, columns
        self._factor = float(factor)
        stored = reader.shape
        self._frames = stored[-2] - start if frames is None else frames
        width = stored[-1] if columns is None else columns.shape[1]
        self.shape = torch.Size((self._frames, width) if batch is not None or len(stored) == 2
                                else (stored[0], self._frames, width))
        self.ndim = len(self.shape)
        self.dtype = torch.float64
        self._any: bool | None = None

    @property
    def stored_dtype(self) -> np.dtype:
        """The dtype on disk (and in each read buffer)."""
        return np.dtype(self._reader.dtype).newbyteorder("=")

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key):
        if self.ndim == 3:
            if not isinstance(key, (int, np.integer)) or not -self.shape[0] <= key < self.shape[0]:
                raise IndexError(f"recording {key!r} of a batch of {self.shape[0]}")
            return FrameArray(self._reader, int(key) % self.shape[0], self._start, self._frames, self._columns,
                              self._factor)
        if not isinstance(key, slice) or key.step not in (None, 1):
            raise TypeError("streamed telemetry reads contiguous frames only: index it with a[start:stop]")
        start, stop, _ = key.indices(self._frames)
        return self._read(start, max(start, stop))

    def narrow(self, dim: int, start: int, length: int) -> FrameArray:
        """Frames ``start .. start + length - 1`` as a lazy view (``torch.Tensor.narrow`` on dimension 0)."""
        if dim != 0 or self.ndim != 2 or start < 0 or length < 0 or start + length > self._frames:
            raise IndexError(f"narrow({dim}, {start}, {length}) of a {tuple(self.shape)} frame array")
        return FrameArray(self._reader, self._batch, self._start + start, length, self._columns, self._factor)

    def scaled(self, factor: float) -> FrameArray:
        """This array with every value multiplied by ``factor`` (lazy)."""
        return FrameArray(self._reader, self._batch, self._start, self._frames, self._columns, self._factor * factor)

    def _read(self, start: int, stop: int) -> torch.Tensor:
        raw = self._reader.read(self._batch or 0, self._start + start, self._start + stop)
        block = torch.from_numpy(raw.astype(np.float64))
        if self._reader.scale is not None:
            block = block * self._reader.scale[0] + self._reader.scale[1]
        block = block if self._columns is None else block @ self._columns
        return block if self._factor == 1.0 else block * self._factor

    def blocks(self, block_frames: int = SCAN_FRAMES):
        """``(first frame, float64 block)`` over the whole (2-d) array."""
        for a in range(0, self._frames, block_frames):
            yield a, self[a: a + block_frames]

    def scan(self, name: str, where: str, block_frames: int = SCAN_FRAMES) -> bool:
        """One pass over the stored values (no float64 copy): one :class:`TelemetryError` line at the first block
        holding NaN or inf; returns (and remembers) whether any value is non-zero."""
        nonzero = False
        for a in range(0, self._frames, block_frames):
            raw = self._reader.read(self._batch or 0, self._start + a, self._start + min(a + block_frames, self._frames))
            if raw.dtype.kind == "f" and not np.isfinite(raw).all():
                raise TelemetryError(f"{where}: array {name!r} holds {int((~np.isfinite(raw)).sum())} non-finite "
                                     f"values (NaN or inf) in frames {a} .. {a + raw.shape[0] - 1}")
            if not nonzero:  # stored zeros are zeros unless scaled (FITS BZERO) or mapped (slopes -> wfs)
                plain = self._reader.scale is None and self._columns is None
                nonzero = bool(raw.any()) if plain else bool(self._read(a, a + raw.shape[0]).any())
        self._any = nonzero
        return nonzero

    def any(self) -> bool:
        """Whether any value is non-zero (one pass; remembered). Recordings of a batch are scanned in turn."""
        if self._any is None:
            recordings = [self] if self.ndim == 2 else [self[i] for i in range(self.shape[0])]
            self._any = any(rec.scan("", "telemetry") for rec in recordings)
        return self._any


class StreamedTelemetry:
    """A telemetry file read in blocks of frames (the module docstring): ``y`` and ``wfs`` are :class:`FrameArray` s.

    Use it wherever training and identification take :class:`~eofnn.telemetry.record.Telemetry`
    (:func:`eofnn.training.from_telemetry.fit_from_telemetry`, :func:`eofnn.training.identify.identify_plant`);
    :meth:`load` reads it whole when something needs tensors.

    Attributes
    ----------
    path : Path
    y, wfs : FrameArray
        ``(frames, K)`` or ``(batch, frames, K)``, float64 blocks when sliced (nm).
    delay_frames, config, frame_rate_hz, positions_m, modal_basis, measurement
        As in :class:`~eofnn.telemetry.record.Telemetry`.
    """

    def __init__(self, path: Path, y: FrameArray, wfs: FrameArray, meta: Telemetry) -> None:
        self.path, self.y, self.wfs = path, y, wfs
        self.s = self.eps = None
        self.delay_frames, self.config, self.frame_rate_hz = meta.delay_frames, meta.config, meta.frame_rate_hz
        self.positions_m, self.modal_basis, self.measurement = meta.positions_m, meta.modal_basis, meta.measurement
        self._checked = False
        self._sequences: list[StreamedTelemetry] | None = None

    @classmethod
    def open(cls, path: str | Path, space: dict | None = None) -> StreamedTelemetry:
        """Read the header and small arrays of ``path`` (``.fits`` or ``.npz``, the layout of ``docs/telemetry.md``)
        and locate ``y`` and ``wfs`` (or ``slopes``); ``space`` as in :meth:`Telemetry.load`. Refused with one
        :class:`TelemetryError` line: what :meth:`Telemetry.load` refuses, plus arrays stored so that frames are not
        contiguous (Fortran order, compressed FITS images)."""
        path, where, suffix = telemetry_path(path)
        try:
            if suffix == ".npz":
                _, positions, delay, rate, meta, found = _read_npz(path, skip=STREAMED)
                readers = npz_readers(path)
            else:
                _, positions, delay, rate, meta, found = _read_fits(path, skip=STREAMED)
                readers = fits_readers(path)
        except TelemetryError:
            raise
        except (OSError, ValueError, KeyError, TypeError, EOFError, struct.error, zipfile.BadZipFile,
                json.JSONDecodeError) as err:
            raise TelemetryError(f"{where} is not readable as {suffix[1:]} telemetry "
                                 f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})") from None
        space = {**found, **(space or {})}
        columns = seen = None
        measurement = ""
        if "wfs" not in readers and "slopes" in readers and "y" in readers:
            if readers["slopes"].shape[:-1] != readers["y"].shape[:-1]:
                raise TelemetryError(f"{where}: slopes have shape {readers['slopes'].shape} but y "
                                     f"{readers['y'].shape}: expected the same frames (and batch), one row of slopes "
                                     "per frame")
            r, measurement, seen = slopes_reconstructor(readers["slopes"].shape[-1], readers["y"].shape[-1],
                                                        space.get("interaction_matrix"), space.get("reconstructor"),
                                                        float(space.get("rcond", RCOND)))
            columns = r.T.contiguous()
            readers["wfs"] = readers.pop("slopes")
        missing = [name for name in TELEMETRY_REQUIRED if name not in readers]
        if missing:
            raise TelemetryError(f"{where} lacks array(s) {', '.join(missing)}"
                                 + (" (or slopes with an interaction_matrix or reconstructor)" if "wfs" in missing
                                    else ""))
        y, wfs = FrameArray(readers["y"], columns=seen), FrameArray(readers["wfs"], columns=columns)
        for name, array in (("y", y), ("wfs", wfs)):
            if array.ndim not in (2, 3):
                raise TelemetryError(f"telemetry array {name!r} has shape {tuple(array.shape)}: expected (frames, "
                                     "actuators) or (batch, frames, actuators)")
        if y.shape != wfs.shape:
            raise TelemetryError(f"telemetry array 'wfs' has shape {tuple(wfs.shape)}, others {tuple(y.shape)}")
        if delay is None:
            delay = meta.get("delay_frames")
        if delay is None:
            raise TelemetryError(f"{where} lacks the loop delay: set header key DELAY (FITS) or array delay_frames "
                                 "(npz) to an integer >= 1 (frames)")
        # The header and small arrays are checked as Telemetry checks them (an array-less Telemetry).
        info = Telemetry(delay_frames=_delay(delay, f"{where}: delay_frames"), config=meta.get("config", {}),
                         frame_rate_hz=rate, modal_basis=space.get("modal_basis"), measurement=measurement)
        if info.modal_basis is not None and info.modal_basis.shape[1] != y.shape[-1]:
            Telemetry(y=torch.zeros(1, y.shape[-1]), modal_basis=info.modal_basis)  # its one-line error
        if positions is not None:
            Telemetry(y=torch.zeros(1, y.shape[-1]), positions_m=positions, modal_basis=info.modal_basis)
            info.positions_m = positions
        return cls(path, y, wfs, info)

    @property
    def batched(self) -> bool:
        return self.y.ndim == 3

    @property
    def n_frames(self) -> int:
        return self.y.shape[-2]

    @property
    def stored_bytes(self) -> int:
        """Bytes of ``y`` and ``wfs`` (or slopes) on disk."""
        return sum(a._reader.dtype.itemsize * int(np.prod(a._reader.shape)) for a in (self.y, self.wfs))

    def arrays(self) -> dict[str, FrameArray]:
        return {"y": self.y, "wfs": self.wfs}

    def realisation(self, index: int) -> StreamedTelemetry:
        one = StreamedTelemetry(self.path, self.y[index], self.wfs[index], self)
        one._checked = self._checked
        return one

    def sequences(self) -> list[StreamedTelemetry]:
        """The independent ``(frames, K)`` recordings (lazy; the same objects on every call)."""
        if self._sequences is None:
            self._sequences = [self] if not self.batched else [self.realisation(i) for i in range(self.y.shape[0])]
        return self._sequences

    def scaled(self, command: float, measurement: float) -> StreamedTelemetry:
        """This file with ``y`` multiplied by ``command`` and ``wfs`` by ``measurement`` (lazy): a record's units
        converted to nm (:mod:`eofnn.telemetry.units`)."""
        one = StreamedTelemetry(self.path, self.y.scaled(command), self.wfs.scaled(measurement), self)
        one._checked = self._checked
        return one

    def shifted(self, lag: int) -> StreamedTelemetry:
        """This (2-d) recording with ``wfs`` ``lag`` frames earlier: ``y[:-lag]`` beside ``wfs[lag:]`` (lazy)."""
        frames = self.n_frames - lag
        one = StreamedTelemetry(self.path, self.y.narrow(0, 0, frames), self.wfs.narrow(0, lag, frames), self)
        one._checked = self._checked
        return one

    def check(self, block_frames: int = SCAN_FRAMES) -> None:
        """One pass over every block: non-finite values are refused with one line naming the array and frame; the
        non-zero flags of :meth:`FrameArray.any` are remembered."""
        if self._checked:
            return
        for seq in self.sequences():
            if seq is not self and seq._checked:
                continue
            for name, array in seq.arrays().items():
                array.scan("slopes" if name == "wfs" and array._columns is not None else name,
                           f"telemetry file {str(self.path)!r}", block_frames)
            seq._checked = True
        self._checked = True

    def load(self) -> Telemetry:
        """The whole file in memory, as :meth:`Telemetry.load` reads it."""
        read = (lambda a: a[:]) if not self.batched else (lambda a: torch.stack([a[i][:] for i in range(len(a))]))
        one = Telemetry(y=read(self.y), wfs=read(self.wfs), delay_frames=self.delay_frames, config=self.config,
                        frame_rate_hz=self.frame_rate_hz, measurement=self.measurement)
        one.positions_m, one.modal_basis = self.positions_m, self.modal_basis
        return one

    def __repr__(self) -> str:
        return (f"StreamedTelemetry({str(self.path)!r}, y {tuple(self.y.shape)} {self.y.stored_dtype}, "
                f"delay_frames={self.delay_frames})")
