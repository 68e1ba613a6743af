"""Telemetry: the arrays ``s, y, eps, wfs`` of a loop run, saved as FITS (the AO convention) or ``.npz``.

Arrays are ``(frames, n_actuators)`` or ``(batch, frames, n_actuators)``, in nm:

- ``s``: turbulence (piston/tip/tilt removed),
- ``y``: DM commands as the controller believes them (the command computed for frame ``n``),
- ``eps``: true residual ``s + DM(y)`` (for a fractional delay ``d + f``, the DM term is the average
  ``(1 - f) DM(y(n)) + f DM(y(n - 1))`` acting over the frame, :mod:`eofnn.delay`),
- ``wfs``: what the WFS reported of ``eps`` (equal to ``eps`` for a perfect sensor).

Files from other simulators or a real-time computer need only ``y`` and ``wfs`` (or ``slopes`` with an interaction
matrix or a reconstructor, :mod:`eofnn.telemetry.spaces`) and the loop delay; ``y`` and ``wfs`` may be modal coefficients
of a ``modal_basis``. A loop that measures slopes (eofnn's Shack-Hartmann) writes them, with its interaction matrix and
reconstructor, beside ``y`` and ``wfs``: readers use ``wfs`` when present. The layout (HDU names, header keys, npz
keys) is documented in ``docs/telemetry.md``.
"""

from __future__ import annotations

import json
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eofnn.delay import check_delay
from eofnn.errors import ConfigError, TelemetryError
from eofnn.lazy import lazy_module
from eofnn.outputs import check_output_file
from eofnn.telemetry.positions import check_positions
from eofnn.telemetry.spaces import RCOND, check_modal_basis, residual_from_slopes

torch = lazy_module("torch")

ARRAYS = ("s", "y", "eps", "wfs")
#: What training, identification and replay from telemetry alone need.
TELEMETRY_REQUIRED = ("y", "wfs")
#: FITS primary-header keywords (8-character standard ones first, HIERARCH long names accepted too).
DELAY_KEYS = ("DELAY", "DELAY_FRAMES")
FRAME_RATE_KEYS = ("FRATE", "FRAME_RATE_HZ")
#: Arrays of the spaces real loops record (docs/telemetry.md): slopes and the matrices that bring them to ``wfs``.
SPACE_ARRAYS = ("slopes", "interaction_matrix", "reconstructor", "modal_basis")
#: Those a :class:`Telemetry` carries as the sensor's own, written beside ``y`` and ``wfs``.
SENSOR_ARRAYS = ("slopes", "interaction_matrix", "reconstructor")


@dataclass
class Telemetry:
    """Arrays of one loop run plus the configuration that made them.

    Attributes
    ----------
    s, y, eps, wfs : Tensor or None
        ``(frames, K)`` or ``(batch, frames, K)`` float64 arrays in nm (see the module docstring).
    delay_frames : int or float
        Loop delay ``tau = d + f``: ``y(n)`` may use ``wfs`` up to frame ``n - d``; a fraction ``f`` of each frame
        still sees the previous command (:mod:`eofnn.delay`).
    config : dict
        What made the run (eofnn writes the plant and scenario here).
    frame_rate_hz : float or None
        Loop frame rate in Hz, when known.
    positions_m : Tensor or None
        ``(K, 2)`` actuator (x, y) positions in metres, when known (neighbourhood filters need them).
    modal_basis : Tensor or None
        ``(K, M)``: ``y`` and ``wfs`` are coefficients of these ``M`` modes (actuator commands ``B @ y``); None for
        actuator-space telemetry.
    measurement : str
        How ``wfs`` was formed when it was not recorded as such (e.g. from slopes); empty otherwise.
    slopes, interaction_matrix, reconstructor : Tensor or None
        The sensor's own measurements ``(frames, S)`` or ``(batch, frames, S)`` and its matrices ``(S, K)`` and
        ``(K, S)`` (``docs/telemetry.md``), when it measures slopes: saved beside the arrays, read back from a file.
    """

    s: torch.Tensor | None = None
    y: torch.Tensor | None = None
    eps: torch.Tensor | None = None
    wfs: torch.Tensor | None = None
    delay_frames: int | float = 2
    config: dict = field(default_factory=dict)
    frame_rate_hz: float | None = None
    positions_m: torch.Tensor | None = None
    modal_basis: torch.Tensor | None = None
    measurement: str = ""
    slopes: torch.Tensor | None = None
    interaction_matrix: torch.Tensor | None = None
    reconstructor: torch.Tensor | None = None

    def __post_init__(self) -> None:
        shape = None
        for name in ARRAYS:
            value = getattr(self, name)
            if value is None:
                continue
            value = _real_tensor(value, name)
            setattr(self, name, value)
            if value.ndim not in (2, 3):
                raise TelemetryError(
                    f"telemetry array {name!r} has shape {tuple(value.shape)}: expected (frames, actuators) "
                    "or (batch, frames, actuators)"
                )
            if shape is not None and tuple(value.shape) != shape:
                raise TelemetryError(f"telemetry array {name!r} has shape {tuple(value.shape)}, others {shape}")
            shape = tuple(value.shape)
        self.delay_frames = _delay(self.delay_frames, "delay_frames")
        if self.frame_rate_hz is not None:
            rate = _number(self.frame_rate_hz, "frame_rate_hz")
            if not rate > 0:
                raise TelemetryError(f"telemetry frame_rate_hz={self.frame_rate_hz!r} is invalid: it must be > 0 (Hz)")
            self.frame_rate_hz = rate
        if self.modal_basis is not None:
            self.modal_basis = check_modal_basis(self.modal_basis, shape[-1] if shape else np.shape(self.modal_basis)[1])
        if self.positions_m is not None:
            self.positions_m = _real_tensor(self.positions_m, "positions_m")
            n_act = self.modal_basis.shape[0] if self.modal_basis is not None else None if shape is None else shape[-1]
            if self.positions_m.ndim != 2 or self.positions_m.shape[1] != 2 or (
                    n_act is not None and self.positions_m.shape[0] != n_act):
                raise TelemetryError(f"telemetry positions_m has shape {tuple(self.positions_m.shape)}: expected "
                                     f"({n_act if n_act is not None else 'actuators'}, 2) actuator (x, y) in metres")
            check_positions(self.positions_m)  # duplicates, fewer than 4
        self._check_sensor_arrays(shape)

    def _check_sensor_arrays(self, shape: tuple | None) -> None:
        """Slopes: one row per frame of the arrays; the matrices: ``(S, K)`` and ``(K, S)``; else one line."""
        if self.slopes is not None:
            self.slopes = _real_tensor(self.slopes, "slopes")
            if self.slopes.ndim not in (2, 3) or (shape is not None and tuple(self.slopes.shape[:-1]) != shape[:-1]):
                raise TelemetryError(f"telemetry slopes have shape {tuple(self.slopes.shape)} but the arrays "
                                     f"{shape}: expected the same frames (and batch), one row of slopes per frame")
        n_slopes = None if self.slopes is None else self.slopes.shape[-1]
        n_cmd = None if shape is None else shape[-1]
        for name, rows, cols, relation in (("interaction_matrix", n_slopes, n_cmd, "slopes = IM @ y"),
                                           ("reconstructor", n_cmd, n_slopes, "wfs = R @ slopes")):
            value = getattr(self, name)
            if value is None:
                continue
            value = _real_tensor(value, name)
            if value.ndim != 2 or (rows or value.shape[0], cols or value.shape[1]) != tuple(value.shape):
                raise TelemetryError(f"telemetry {name} has shape {tuple(value.shape)}: expected "
                                     f"({rows or 'S'}, {cols or 'K'}) ({relation}, {n_slopes} slopes, {n_cmd} columns "
                                     "of y)")
            setattr(self, name, value)

    @classmethod
    def from_slopes(cls, y, slopes, *, interaction_matrix=None, reconstructor=None, rcond: float = RCOND,
                    **fields) -> Telemetry:
        """Telemetry whose ``wfs`` is formed from ``slopes`` (``(..., frames, S)``) with an interaction matrix
        ``(S, K)`` or a reconstructor ``(K, S)`` (:func:`eofnn.telemetry.spaces.residual_from_slopes`); ``fields`` are the
        other attributes (``delay_frames``, ``positions_m``, ``modal_basis``, ...)."""
        y = _real_tensor(y, "y")
        slopes = _real_tensor(slopes, "slopes")
        if slopes.shape[:-1] != y.shape[:-1]:
            raise TelemetryError(f"telemetry slopes have shape {tuple(slopes.shape)} but y {tuple(y.shape)}: expected "
                                 "the same frames (and batch), one row of slopes per frame")
        wfs, note, seen = residual_from_slopes(slopes, y.shape[-1], interaction_matrix, reconstructor, rcond)
        return cls(y=y if seen is None else y @ seen, wfs=wfs, measurement=note, **fields)

    def arrays(self) -> dict[str, torch.Tensor]:
        """The arrays present, by name."""
        return {name: getattr(self, name) for name in ARRAYS if getattr(self, name) is not None}

    @property
    def batched(self) -> bool:
        """Whether the arrays are ``(batch, frames, K)``."""
        return next(iter(self.arrays().values())).ndim == 3

    def realisation(self, index: int) -> Telemetry:
        """One realisation of batched telemetry as ``(frames, actuators)`` arrays."""
        one = Telemetry(**{k: v[index] for k, v in self.arrays().items()}, delay_frames=self.delay_frames,
                        config=self.config, frame_rate_hz=self.frame_rate_hz, measurement=self.measurement)
        one.positions_m, one.modal_basis = self.positions_m, self.modal_basis  # checked already (the basis by an SVD)
        one.interaction_matrix, one.reconstructor = self.interaction_matrix, self.reconstructor
        one.slopes = None if self.slopes is None else self.slopes[index] if self.slopes.ndim == 3 else self.slopes
        return one

    def sensor_arrays(self) -> dict[str, torch.Tensor]:
        """The sensor's own arrays present (:data:`SENSOR_ARRAYS`), by name."""
        return {name: getattr(self, name) for name in SENSOR_ARRAYS if getattr(self, name) is not None}

    def sequences(self) -> list[Telemetry]:
        """The independent sequences of this telemetry: its realisations, each ``(frames, K)``."""
        if not self.batched:
            return [self]
        return [self.realisation(i) for i in range(next(iter(self.arrays().values())).shape[0])]

    def save(self, path: str | Path, overwrite: bool = False, dtype: str = "float64") -> Path:
        """Write to ``.fits`` or ``.npz`` (by suffix); refuses to overwrite an existing file unless asked.

        ``dtype="float32"`` halves the file (telemetry values are nm: float32 keeps 7 significant digits, far below
        any WFS noise); arrays are read back as float64 either way.
        """
        path = check_output_file(path, overwrite)
        meta = json.dumps({"delay_frames": self.delay_frames, "config": self.config})
        if path.suffix.lower() in (".fits", ".fit"):
            from astropy.io import fits

            primary = fits.PrimaryHDU()
            primary.header["EOFNN"] = (1, "eofnn telemetry format version")
            primary.header["DELAY"] = (self.delay_frames, "loop delay in frames")
            if self.frame_rate_hz is not None:
                primary.header["FRATE"] = (self.frame_rate_hz, "loop frame rate in Hz")
            primary.header["BUNIT"] = "nm"
            hdus = [primary]
            for name, value in self.arrays().items():
                hdus.append(fits.ImageHDU(value.numpy().astype(dtype), name=name.upper()))
            if self.positions_m is not None:
                hdus.append(fits.ImageHDU(self.positions_m.numpy(), name="POSITIONS"))
            if self.modal_basis is not None:
                hdus.append(fits.ImageHDU(self.modal_basis.numpy(), name="MODAL_BASIS"))
            for name, value in self.sensor_arrays().items():  # slopes in the arrays' dtype, matrices in float64
                hdus.append(fits.ImageHDU(value.numpy().astype(dtype if name == "slopes" else "float64"),
                                          name=name.upper()))
            hdus.append(fits.BinTableHDU.from_columns(
                [fits.Column(name="json", format=f"{max(len(meta), 1)}A", array=np.array([meta]))], name="CONFIG"))
            fits.HDUList(hdus).writeto(path, overwrite=overwrite)
        elif path.suffix.lower() == ".npz":
            extra = {"delay_frames": np.array(self.delay_frames)}
            if self.frame_rate_hz is not None:
                extra["frame_rate_hz"] = np.array(self.frame_rate_hz)
            if self.positions_m is not None:
                extra["positions_m"] = self.positions_m.numpy()
            if self.modal_basis is not None:
                extra["modal_basis"] = self.modal_basis.numpy()
            for name, value in self.sensor_arrays().items():
                extra[name] = value.numpy().astype(dtype if name == "slopes" else "float64")
            np.savez(path, meta=np.array(meta), **extra, **{k: v.numpy().astype(dtype) for k, v in self.arrays().items()})
        else:
            raise TelemetryError(f"telemetry file {str(path)!r} has suffix {path.suffix!r}: allowed are .fits, .npz")
        return path

    @classmethod
    def load(cls, path: str | Path, required: tuple[str, ...] = ARRAYS, space: dict | None = None) -> Telemetry:
        """Read a telemetry file in the layout of ``docs/telemetry.md`` (what :meth:`save` writes is one).

        Missing ``required`` arrays, bad shapes, NaNs, complex or text arrays, a missing or non-integer delay and
        unreadable files raise :class:`TelemetryError` with one line.
        """
        path, where, suffix = telemetry_path(path)
        try:
            arrays, positions, delay, rate, meta, found = (_read_fits if suffix != ".npz" else _read_npz)(path)
        except TelemetryError:
            raise
        except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, json.JSONDecodeError) as err:
            raise TelemetryError(f"{where} is not readable as {suffix[1:]} telemetry "
                                 f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})") from None
        space = {**found, **(space or {})}  # matrices given beside the file replace the file's own
        measurement = ""
        if "slopes" in space and "wfs" not in arrays:
            if "y" not in arrays:
                raise TelemetryError(f"{where} lacks array(s) y")
            if space["slopes"].shape[:-1] != arrays["y"].shape[:-1]:
                raise TelemetryError(f"{where}: slopes have shape {tuple(space['slopes'].shape)} but y "
                                     f"{tuple(arrays['y'].shape)}: expected the same frames (and batch), one row of "
                                     "slopes per frame")
            arrays["wfs"], measurement, seen = residual_from_slopes(
                space["slopes"], arrays["y"].shape[-1], space.get("interaction_matrix"), space.get("reconstructor"),
                float(space.get("rcond", RCOND)))
            if seen is not None:
                arrays["y"] = arrays["y"] @ seen
        missing = [name for name in required if name not in arrays]
        if missing:
            raise TelemetryError(f"{where} lacks array(s) {', '.join(missing)}"
                                 + (" (or slopes with an interaction_matrix or reconstructor)" if "wfs" in missing
                                    else ""))
        if delay is None:
            delay = meta.get("delay_frames")
        # Arrays are checked first (shapes, values), then the delay: a file with both wrong names its arrays.
        telemetry = cls(**arrays, delay_frames=1 if delay is None else _delay(delay, f"{where}: delay_frames"),
                        config=meta.get("config", {}), frame_rate_hz=rate, positions_m=positions,
                        modal_basis=space.get("modal_basis"), measurement=measurement,
                        **{name: found[name] for name in SENSOR_ARRAYS if name in found})
        if delay is None:
            raise TelemetryError(f"{where} lacks the loop delay: set header key DELAY (FITS) or array delay_frames "
                                 "(npz) to an integer >= 1 (frames)")
        return telemetry


def telemetry_path(path: str | Path) -> tuple[Path, str, str]:
    """``(path, where, suffix)`` of a telemetry file to read: one :class:`TelemetryError` line unless it exists and is
    ``.fits``/``.fit``/``.npz`` (``where`` names it in messages; ``suffix`` is lower case)."""
    path = Path(path)
    where = f"telemetry file {str(path)!r}"
    if not path.exists():
        raise TelemetryError(f"{where} does not exist")
    suffix = path.suffix.lower()
    if suffix not in (".fits", ".fit", ".npz"):
        raise TelemetryError(f"{where} has suffix {path.suffix!r}: allowed are .fits, .npz")
    return path, where, suffix


def _real_tensor(value, name: str) -> torch.Tensor:
    """A finite float64 tensor of real numbers, or one line saying why not."""
    if isinstance(value, np.ndarray) and value.dtype.kind not in "fiu":
        raise TelemetryError(f"telemetry array {name!r} has dtype {value.dtype}: it must hold real numbers (nm)")
    value = torch.as_tensor(value)
    if value.is_complex() or value.dtype == torch.bool:
        raise TelemetryError(f"telemetry array {name!r} has dtype {value.dtype}: it must hold real numbers (nm)")
    value = value.to(torch.float64)
    if not torch.isfinite(value).all():
        bad = int((~torch.isfinite(value)).sum())
        raise TelemetryError(f"telemetry array {name!r} holds {bad} non-finite values (NaN or inf)")
    return value


def _number(value, name: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TelemetryError(f"telemetry {name}={value!r} is invalid: it must be a number")
    return float(value)


def _delay(value, name: str) -> int | float:
    """The loop delay in frames, a finite number in [1, 100]: an int when integral (FITS ``2.0`` -> 2)."""
    if isinstance(value, (np.ndarray, np.generic)) and np.ndim(value) == 0:
        value = value.item()
    try:
        return check_delay(value, name)
    except ConfigError as err:
        raise TelemetryError(str(err)) from None


def _array(data, name: str) -> np.ndarray:
    data = np.asarray(data)
    if data.dtype.kind not in "fiu":
        raise TelemetryError(f"telemetry array {name!r} has dtype {data.dtype}: it must hold real numbers (nm)")
    return data.astype(np.float64)


def _read_fits(path: Path, skip: tuple[str, ...] = ()):
    """Arrays, positions, delay, frame rate, config and space matrices of a FITS file; arrays named in ``skip``
    are left unread (streamed telemetry reads them block by block)."""
    from astropy.io import fits

    arrays, positions, delay, rate, meta, space = {}, None, None, None, {}, {}
    # astropy only warns about truncated or corrupt files and returns what it could read: make that an error.
    with warnings.catch_warnings(record=True) as caught, fits.open(path, memmap=False) as hdul:
        warnings.simplefilter("always")
        header = hdul[0].header
        names = {hdu.name for hdu in hdul}
        for name in ARRAYS:
            if name not in skip and name.upper() in names and hdul[name.upper()].data is not None:
                arrays[name] = torch.from_numpy(_array(hdul[name.upper()].data, name))
        if "POSITIONS" in names:
            positions = torch.from_numpy(_array(hdul["POSITIONS"].data, "positions_m"))
        for name in SPACE_ARRAYS:
            if name not in skip and name.upper() in names and hdul[name.upper()].data is not None:
                space[name] = torch.from_numpy(_array(hdul[name.upper()].data, name))
        if "RCOND" in header:
            space["rcond"] = _number(header["RCOND"], "rcond")
        delay = next((header[k] for k in DELAY_KEYS if k in header), None)
        rate = next((header[k] for k in FRAME_RATE_KEYS if k in header), None)
        if "CONFIG" in names:
            meta = json.loads(hdul["CONFIG"].data["json"][0])
    problems = [str(w.message).splitlines()[0] for w in caught if "astropy" in type(w.message).__module__]
    if problems:
        raise TelemetryError(f"telemetry file {str(path)!r} is truncated or corrupt ({problems[0]})")
    return arrays, positions, delay, rate, meta, space


def _read_npz(path: Path, skip: tuple[str, ...] = ()):
    """What :func:`_read_fits` reads, from an ``.npz`` file (members are read only when accessed)."""
    arrays, positions, delay, rate, meta, space = {}, None, None, None, {}, {}
    with np.load(path, allow_pickle=False) as data:
        for name in ARRAYS:
            if name not in skip and name in data.files:
                arrays[name] = torch.from_numpy(_array(data[name], name))
        if "positions_m" in data.files:
            positions = torch.from_numpy(_array(data["positions_m"], "positions_m"))
        for name in SPACE_ARRAYS:
            if name not in skip and name in data.files:
                space[name] = torch.from_numpy(_array(data[name], name))
        if "rcond" in data.files:
            space["rcond"] = _number(data["rcond"].item(), "rcond")
        if "delay_frames" in data.files:
            delay = data["delay_frames"]
        if "frame_rate_hz" in data.files:
            rate = data["frame_rate_hz"].item() if data["frame_rate_hz"].ndim == 0 else data["frame_rate_hz"]
        if "meta" in data.files:
            meta = json.loads(str(data["meta"]))
    return arrays, positions, delay, rate, meta, space
