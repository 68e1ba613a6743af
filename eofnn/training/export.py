"""Export a fitted linear filter as FITS (layout: ``docs/export.md``), for :mod:`eofnn.runtime` or any other RTC."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.models.linear import LinearFilter
from eofnn.outputs import check_output_file, staged_file
from eofnn.runtime import FORMAT_VERSION


def filter_taps(spec: HistorySpec) -> list[tuple[str, int]]:
    """``(signal, lag)`` of each tap of a ``spec`` history, in the order of :mod:`eofnn.data.history`."""
    d, p = spec.delay_frames, spec.history_length
    if spec.kind == "open_loop":
        return [("pol", lag) for lag in range(d, d + p)]
    return [("y", lag) for lag in range(1, p + 1)] + [("wfs", lag) for lag in range(d, d + p)]


def filter_coefficients(network: LinearFilter) -> tuple[np.ndarray, np.ndarray | None]:
    """``(K, taps)`` coefficients (a shared filter repeated per actuator), or ``(K, M, taps)`` plus ``(K, M)``
    neighbour indices with ``-1`` beyond the pupil edge."""
    weight = network.weight.detach().to(torch.float64).cpu().numpy()
    k, taps = network.n_actuators, network.n_taps
    if network.structure == "shared":
        return np.repeat(weight, k, axis=0), None
    if network.structure == "neighbourhood":
        neighbours = network.neighbours.cpu().numpy()
        return weight.reshape(k, neighbours.shape[1], taps), np.where(neighbours >= k, -1, neighbours)
    if network.structure == "modal":  # every actuator reads every actuator: F_t = B diag(w_t) B^T per tap
        modes = network.modes.detach().to(torch.float64).cpu().numpy()
        return np.einsum("im,mt,jm->ijt", modes, weight, modes), np.tile(np.arange(k), (k, 1))
    return weight, None


def export_filter(network: LinearFilter, spec: HistorySpec, path: str | Path, *, dm_gain_model: float = 1.0,
                  positions_m: np.ndarray | torch.Tensor | None = None, overwrite: bool = False,
                  info: dict | None = None) -> Path:
    """Write ``network`` (a :class:`~eofnn.models.linear.LinearFilter` reading ``spec`` histories) as filter FITS.

    Parameters
    ----------
    network : LinearFilter
        The fitted filter (any structure).
    spec : HistorySpec
        The history it reads.
    path : path
        ``.fits`` file to write; an existing one is kept unless ``overwrite``.
    dm_gain_model : float
        DM gain of the pseudo-open-loop reconstruction (open-loop filters: the identified gain).
    positions_m : array, optional
        ``(K, 2)`` actuator positions in metres, stored as a POSITIONS image.
    info : dict, optional
        Short string/number items stored as header cards (e.g. where the filter was trained).
    """
    from astropy.io import fits

    if not isinstance(network, LinearFilter):
        raise ConfigError(f"only linear filters can be exported, not {type(network).__name__}")
    if spec.delay_fraction:
        raise ConfigError(f"delay_frames={spec.delay_frames} is invalid for a filter export: eofnn.runtime supports "
                          "integer delays only")
    if network.n_taps != spec.n_taps:
        raise ConfigError(f"network has {network.n_taps} taps but the history {spec.kind} of length "
                          f"{spec.history_length} has {spec.n_taps}")
    path = Path(path)
    if path.suffix.lower() not in (".fits", ".fit"):
        raise ConfigError(f"filter file {str(path)!r} has suffix {path.suffix!r}: allowed are .fits")
    check_output_file(path, overwrite)  # before any work
    coefficients, neighbours = filter_coefficients(network)
    if not np.isfinite(coefficients).all():
        raise ConfigError(f"the filter holds {int((~np.isfinite(coefficients)).sum())} non-finite coefficient(s): "
                          "nothing was written (eofnn.runtime would refuse it)")
    if not (np.isfinite(dm_gain_model) and 0 < dm_gain_model <= 100):
        raise ConfigError(f"dm_gain_model={dm_gain_model!r} is invalid: it must be a number in (0, 100]")
    primary = fits.PrimaryHDU(coefficients)
    cards = [("EOFNNFLT", FORMAT_VERSION, "eofnn linear filter format version"),
             ("HISTKIND", spec.kind, "open_loop (POL) or closed_loop (y, wfs)"),
             ("HISTLEN", spec.history_length, "history length p (taps per signal)"),
             ("DELAY", spec.delay_frames, "loop delay d in frames"),
             ("NACT", network.n_actuators, "actuators K"), ("NTAPS", spec.n_taps, "taps per actuator"),
             ("STRUCT", network.structure, "per_actuator, shared, neighbourhood, modal (all neighbours)"),
             ("DMGAIN", float(dm_gain_model), "DM gain of the POL reconstruction wfs - g y"),
             ("FIRST", spec.first_frame, "zero commands for the first FIRST steps"),
             ("BUNIT", "nm/nm", "coefficients: command nm per input nm"),
             ("INUNIT", "nm", "inputs: commands, WFS residuals (OPD)"),
             ("OUTUNIT", "nm", "output: DM command (OPD)")]
    if network.structure == "neighbourhood":
        cards.append(("RADIUS", float(network.radius), "neighbourhood radius in actuator pitches"))
    for key, value, comment in cards:
        primary.header[key] = (value, comment)
    for key, value in (info or {}).items():
        primary.header[f"HIERARCH EOFNN {key}"] = value
    taps = filter_taps(spec)
    hdus = [primary, fits.BinTableHDU.from_columns([
        fits.Column(name="TAP", format="J", array=np.arange(len(taps))),
        fits.Column(name="SIGNAL", format="3A", array=np.array([s for s, _ in taps])),
        fits.Column(name="LAG", format="J", array=np.array([lag for _, lag in taps]), unit="frame")], name="TAPS")]
    if neighbours is not None:
        hdus.append(fits.ImageHDU(neighbours.astype(np.int32), name="NEIGHBOURS"))
    if positions_m is not None:
        hdus.append(fits.ImageHDU(np.asarray(positions_m, dtype=np.float64), name="POSITIONS"))
    with staged_file(path, overwrite) as partial:
        fits.HDUList(hdus).writeto(partial)
    return path
