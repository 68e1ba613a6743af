"""The spaces real loops record in, and how eofnn brings them to its own: an actuator-space (or modal) residual.

eofnn trains on ``y`` (commands) and ``wfs`` (the measured residual in the same space as ``y``, nm). A real-time
computer records

- *slopes* ``(frames, S)`` (any unit ``u``) with an **interaction matrix** ``IM`` ``(S, K)``: ``slopes = IM @ y`` for
  a command ``y`` on a flat wavefront (``u`` per nm, poked and measured with the sign of the loop), or a
  **reconstructor** ``R`` ``(K, S)`` (nm per ``u``): ``wfs = R @ slopes``. With only ``IM``, eofnn uses the
  least-squares ``R = pinv(IM)``, singular values below ``rcond`` times the largest truncated (modes the sensor does
  not see, e.g. piston and, in Fried geometry, waffle). At most :func:`max_unseen` modes may be truncated (or lie in
  the null space of a given ``R``): more is a singular matrix and a one-line error. The unseen modes are removed
  from ``y`` too (``y <- P y``, ``P`` the projector on the range of ``R``), so that ``wfs = P s + DM(P y)`` stays the
  documented ``s + DM(y)`` in the seen space: otherwise identification reads the missing piston as coupling (a DM
  gain biased low: ``docs/findings.md``) and POL reconstruction adds the commands' unseen modes to ``s_hat``.
- *modal* telemetry: ``y`` and ``wfs`` (or ``slopes`` with a modal ``IM`` ``(S, M)`` / ``R`` ``(M, S)``) in the
  coefficients of a **modal basis** ``B`` ``(K, M)`` whose column ``m`` is the actuator command (nm) of a unit
  coefficient of mode ``m``: predictors run in modes, actuator commands are ``B @ y``. ``B`` must have full column
  rank.

The residual ``R @ slopes(n)`` keeps the frame of ``slopes(n)``: the measurement of frame ``n`` (``docs/telemetry.md``).
"""

from __future__ import annotations

import numpy as np

from eofnn.errors import TelemetryError
from eofnn.lazy import lazy_module

torch = lazy_module("torch")

#: Singular values below this fraction of the largest are truncated from ``pinv(IM)`` (and count as unseen modes).
RCOND = 1e-3


def max_unseen(n_controlled: int) -> int:
    """Modes a sensor may leave unseen before its matrix counts as singular: piston and waffle, plus 5%."""
    return 2 + n_controlled // 20


def _rank_check(singular: np.ndarray, name: str, shape, n_controlled: int, rcond: float, what: str) -> int:
    kept = int((singular > rcond * singular.max()).sum()) if singular.size and singular.max() > 0 else 0
    unseen = n_controlled - kept
    if unseen > max_unseen(n_controlled):
        raise TelemetryError(
            f"telemetry {name} {tuple(shape)} is singular: rank {kept} after truncating singular values below "
            f"rcond={rcond:g} of the largest, so {unseen} of {n_controlled} {what} modes are unseen; allowed: at most "
            f"{max_unseen(n_controlled)} (piston, waffle and 5%), or set a smaller rcond")
    return kept


def _matrix(value, name: str, shape: tuple[int, int] | None = None, why: str = "", relation: str = "") -> np.ndarray:
    """``value`` as a finite float64 matrix, of ``shape`` when given (``why``: what sets that shape; ``relation``:
    the equation the matrix stands in)."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    value = np.asarray(value)
    if value.dtype.kind not in "fiu" or value.ndim != 2:
        raise TelemetryError(f"telemetry {name} has dtype {value.dtype} and shape {value.shape}: it must be a real "
                             "2-d matrix")
    value = value.astype(np.float64)
    if not np.isfinite(value).all():
        raise TelemetryError(f"telemetry {name} holds {int((~np.isfinite(value)).sum())} non-finite values (NaN or inf)")
    if shape is not None and value.shape != shape:
        raise TelemetryError(f"telemetry {name} has shape {value.shape} but {why}: expected {shape} ({relation})")
    return value


def residual_from_slopes(slopes: torch.Tensor, n_controlled: int, interaction_matrix=None, reconstructor=None,
                         rcond: float = RCOND) -> tuple[torch.Tensor, str, torch.Tensor | None]:
    """``(wfs, note, projector)``: the residual ``R @ slopes`` in the ``n_controlled`` command coordinates (actuators
    or modes), ``(..., frames, n_controlled)``, one line saying how it was formed, and the ``(n, n)`` projector on
    the seen modes to apply to ``y`` (None when every mode is seen).

    Parameters
    ----------
    slopes : Tensor
        ``(..., frames, S)`` WFS measurements (any unit ``u``), frame ``n`` measuring the residual of frame ``n``.
    n_controlled : int
        Columns of ``y`` (actuators, or modes of a modal basis).
    interaction_matrix : array_like, optional
        ``(S, n_controlled)``: slopes per nm of command.
    reconstructor : array_like, optional
        ``(n_controlled, S)``: nm per slope unit; used as given when present (the interaction matrix is then only
        checked for shape).
    rcond : float
        Truncation of ``pinv(interaction_matrix)``, relative to the largest singular value.
    """
    r, note, seen = slopes_reconstructor(slopes.shape[-1], n_controlled, interaction_matrix, reconstructor, rcond)
    return slopes.to(torch.float64) @ r.T, note, seen


def slopes_reconstructor(n_slopes: int, n_controlled: int, interaction_matrix=None, reconstructor=None,
                         rcond: float = RCOND) -> tuple[torch.Tensor, str, torch.Tensor | None]:
    """``(R, note, projector)`` of :func:`residual_from_slopes` without the slopes: the ``(n_controlled, n_slopes)``
    reconstructor (``wfs = slopes @ R.T``), the line saying how it was formed, and the projector for ``y`` (None
    when every mode is seen). Streamed telemetry applies them one block of frames at a time."""
    if reconstructor is None and interaction_matrix is None:
        raise TelemetryError("telemetry has slopes but neither an interaction_matrix (slopes = IM @ y) nor a "
                             "reconstructor (wfs = R @ slopes): add one to form the residual")
    if not (0 < rcond < 1):
        raise TelemetryError(f"telemetry rcond={rcond!r} is invalid: it must be in (0, 1)")
    sizes = f"the slopes have {n_slopes} values and y {n_controlled} columns"
    if interaction_matrix is not None:
        im = _matrix(interaction_matrix, "interaction_matrix", (n_slopes, n_controlled), sizes, "slopes = IM @ y")
    if reconstructor is not None:
        r = _matrix(reconstructor, "reconstructor", (n_controlled, n_slopes), sizes, "wfs = R @ slopes")
        u, singular, _ = np.linalg.svd(r, full_matrices=False)
        kept = _rank_check(singular, "reconstructor", r.shape, n_controlled, rcond, "command")
        seen = u[:, :kept]
        note = (f"wfs = R @ slopes with the given reconstructor {r.shape} (rank {kept} of {n_controlled} at "
                f"rcond={rcond:g})")
    else:
        u, singular, vt = np.linalg.svd(im, full_matrices=False)
        kept = _rank_check(singular, "interaction_matrix", im.shape, n_controlled, rcond, "command")
        r = (vt[:kept].T / singular[:kept]) @ u[:, :kept].T
        seen = vt[:kept].T
        note = (f"wfs = pinv(IM) @ slopes, least squares with IM {im.shape}: {n_controlled - kept} mode(s) with "
                f"singular values below rcond={rcond:g} of the largest truncated (unseen: read as 0), condition "
                f"number of the rest {singular[0] / singular[kept - 1]:.3g}")
    if kept == n_controlled:
        return torch.as_tensor(r), note, None
    note += f"; the {n_controlled - kept} unseen mode(s) removed from y too"
    return torch.as_tensor(r), note, torch.as_tensor(seen @ seen.T)


def check_modal_basis(basis, n_modes: int) -> torch.Tensor:
    """``(K, n_modes)`` float64 basis of full column rank, or one :class:`TelemetryError` line."""
    b = _matrix(basis, "modal_basis")
    if b.shape[1] != n_modes or b.shape[0] < n_modes:
        raise TelemetryError(f"telemetry modal_basis has shape {b.shape}: expected (actuators >= {n_modes}, "
                             f"{n_modes}): one column per mode of y (actuator command of a unit coefficient)")
    singular = np.linalg.svd(b, compute_uv=False)
    if singular.min() <= 1e-9 * singular.max():
        rank = int((singular > 1e-9 * singular.max()).sum())
        raise TelemetryError(f"telemetry modal_basis {b.shape} is not of full rank: rank {rank} < {n_modes} modes "
                             "(columns within 1e-9 of dependent); allowed: linearly independent modes")
    return torch.as_tensor(b)


def read_matrix(path, name: str) -> torch.Tensor:
    """A matrix from its own file (``--interaction_matrix FILE``): ``.npy``, ``.npz`` (the array ``name``, or its
    only array) or ``.fits`` (the HDU ``name``, or the first with data); one :class:`TelemetryError` line if not."""
    from pathlib import Path

    path = Path(path)
    where = f"{name} file {str(path)!r}"
    if not path.exists():
        raise TelemetryError(f"{where} does not exist")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            value = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                keys = [name] if name in data.files else data.files
                if len(keys) != 1:
                    raise TelemetryError(f"{where} holds arrays {data.files}: name one {name!r} or keep only one")
                value = data[keys[0]]
        elif suffix in (".fits", ".fit"):
            from astropy.io import fits

            with fits.open(path, memmap=False) as hdul:
                names = [hdu.name for hdu in hdul]
                hdu = hdul[name.upper()] if name.upper() in names else next((h for h in hdul if h.data is not None),
                                                                            None)
                if hdu is None:
                    raise TelemetryError(f"{where} holds no image")
                value = np.array(hdu.data)
        else:
            raise TelemetryError(f"{where} has suffix {path.suffix!r}: allowed are .npy, .npz, .fits")
    except (OSError, ValueError, KeyError, EOFError) as err:
        if isinstance(err, TelemetryError):
            raise
        raise TelemetryError(f"{where} is not readable ({type(err).__name__})") from None
    return torch.as_tensor(_matrix(value, name))


def modal_to_actuators(values: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """``(..., M)`` modal coefficients to ``(..., K)`` actuator values (nm): ``B @ values``."""
    return values.to(torch.float64) @ basis.T
