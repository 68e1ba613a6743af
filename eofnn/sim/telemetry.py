"""Telemetry: the arrays ``s, y, eps, wfs`` of a loop run, saved as FITS (the AO convention) or ``.npz``.

Arrays are ``(frames, n_actuators)`` or ``(batch, frames, n_actuators)``, in nm:

- ``s``: turbulence (piston/tip/tilt removed),
- ``y``: DM commands as the controller believes them,
- ``eps``: true residual ``s + DM(y)``,
- ``wfs``: what the WFS reported of ``eps`` (equal to ``eps`` for a perfect sensor).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from eofnn.errors import TelemetryError
from eofnn.outputs import check_output_file

ARRAYS = ("s", "y", "eps", "wfs")


@dataclass
class Telemetry:
    """Arrays of one loop run plus the configuration that made them."""

    s: torch.Tensor | None = None
    y: torch.Tensor | None = None
    eps: torch.Tensor | None = None
    wfs: torch.Tensor | None = None
    delay_frames: int = 2
    config: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        shape = None
        for name in ARRAYS:
            value = getattr(self, name)
            if value is None:
                continue
            value = torch.as_tensor(value)
            setattr(self, name, value)
            if value.ndim not in (2, 3):
                raise TelemetryError(
                    f"telemetry array {name!r} has shape {tuple(value.shape)}: expected (frames, actuators) "
                    "or (batch, frames, actuators)"
                )
            if shape is not None and tuple(value.shape) != shape:
                raise TelemetryError(f"telemetry array {name!r} has shape {tuple(value.shape)}, others {shape}")
            shape = tuple(value.shape)
            if not torch.isfinite(value).all():
                bad = int((~torch.isfinite(value)).sum())
                raise TelemetryError(f"telemetry array {name!r} holds {bad} non-finite values (NaN or inf)")

    def arrays(self) -> dict[str, torch.Tensor]:
        """The arrays present, by name."""
        return {name: getattr(self, name) for name in ARRAYS if getattr(self, name) is not None}

    def realisation(self, index: int) -> Telemetry:
        """One realisation of batched telemetry as ``(frames, actuators)`` arrays."""
        return Telemetry(**{k: v[index] for k, v in self.arrays().items()}, delay_frames=self.delay_frames,
                         config=self.config)

    def save(self, path: str | Path, overwrite: bool = False) -> Path:
        """Write to ``.fits`` or ``.npz`` (by suffix); refuses to overwrite an existing file unless asked."""
        path = check_output_file(path, overwrite)
        meta = json.dumps({"delay_frames": self.delay_frames, "config": self.config})
        if path.suffix.lower() in (".fits", ".fit"):
            from astropy.io import fits

            primary = fits.PrimaryHDU()
            primary.header["EOFNN"] = (1, "eofnn telemetry format version")
            primary.header["DELAY"] = (self.delay_frames, "loop delay in frames")
            primary.header["BUNIT"] = "nm"
            hdus = [primary]
            for name, value in self.arrays().items():
                hdus.append(fits.ImageHDU(value.numpy(), name=name.upper()))
            hdus.append(fits.BinTableHDU.from_columns(
                [fits.Column(name="json", format=f"{max(len(meta), 1)}A", array=np.array([meta]))], name="CONFIG"))
            fits.HDUList(hdus).writeto(path, overwrite=overwrite)
        elif path.suffix.lower() == ".npz":
            np.savez(path, meta=np.array(meta), **{k: v.numpy() for k, v in self.arrays().items()})
        else:
            raise TelemetryError(f"telemetry file {str(path)!r} has suffix {path.suffix!r}: allowed are .fits, .npz")
        return path

    @classmethod
    def load(cls, path: str | Path, required: tuple[str, ...] = ARRAYS) -> Telemetry:
        """Read a file written by :meth:`save`; missing ``required`` arrays, bad shapes or NaNs raise."""
        path = Path(path)
        if not path.exists():
            raise TelemetryError(f"telemetry file {str(path)!r} does not exist")
        arrays: dict[str, np.ndarray] = {}
        meta = {"delay_frames": 2, "config": {}}
        if path.suffix.lower() in (".fits", ".fit"):
            from astropy.io import fits

            with fits.open(path) as hdul:
                names = {hdu.name for hdu in hdul}
                for name in ARRAYS:
                    if name.upper() in names:
                        arrays[name] = np.asarray(hdul[name.upper()].data, dtype=np.float64)
                if "CONFIG" in names:
                    meta = json.loads(hdul["CONFIG"].data["json"][0])
        elif path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as data:
                for name in ARRAYS:
                    if name in data.files:
                        arrays[name] = np.asarray(data[name], dtype=np.float64)
                if "meta" in data.files:
                    meta = json.loads(str(data["meta"]))
        else:
            raise TelemetryError(f"telemetry file {str(path)!r} has suffix {path.suffix!r}: allowed are .fits, .npz")
        missing = [name for name in required if name not in arrays]
        if missing:
            raise TelemetryError(f"telemetry file {str(path)!r} lacks array(s) {', '.join(missing)}")
        return cls(**{k: torch.from_numpy(v) for k, v in arrays.items()}, delay_frames=int(meta["delay_frames"]),
                   config=meta.get("config", {}))
