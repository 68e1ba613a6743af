"""Training data from telemetry alone: pseudo-open-loop reconstruction and targets through an identified DM.

A telescope has ``y`` (commands) and ``wfs`` (sensor residuals), never the turbulence ``s`` or the true DM. With a
DM response ``DM_model`` identified from the dither (:func:`eofnn.training.identify.identify_plant`):

- POL reconstruction: ``s_hat(n) = wfs(n) - DM_model(y(n))``  (equal to ``s(n)`` plus WFS noise when the model is
  right, since ``wfs(n) = s(n) + DM(y(n)) + noise``);
- target of frame ``n``: the command that would have cancelled it, ``-s_hat(n) / g`` with the identified global
  gain ``g`` (the telemetry twin of the simulator-truth :func:`eofnn.data.history.targets` ``-s(n) / g``);
- a fractional delay ``d + f`` (:mod:`eofnn.delay`): the DM term is the average over the frame,
  ``(1 - f) DM_model(y(n)) + f DM_model(y(n-1))``, and the target ``-((1 - f) s_hat(n) + f s_hat(n+1)) / g``;
- open-loop histories from ``s_hat``; closed-loop histories from ``y`` and ``wfs`` as recorded (no model needed).

The noise in ``s_hat(n)`` is independent of every history that predicts frame ``n`` (they use ``wfs`` up to
``n - d``), so it adds variance to the targets but no bias to a least-squares fit.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path

import torch
from torch.utils.data import IterableDataset

from eofnn.data.history import HistorySpec, applied_command, blended_target, build_history, open_loop_history
from eofnn.errors import TelemetryError
from eofnn.resources import require_memory
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.layout import ActuatorLayout, layout_from_dict, layout_from_positions
from eofnn.sim.sensing.constants import MECHANICAL_COUPLING
from eofnn.sim.sensing.least_squares import surface_per_command
from eofnn.telemetry.file import NotStreamableError, StreamedTelemetry
from eofnn.telemetry.record import TELEMETRY_REQUIRED, Telemetry
from eofnn.telemetry.spaces import read_matrix
from eofnn.telemetry.units import conversion

#: One recording (in memory, or a file read in blocks of frames).
AnyTelemetry = Telemetry | StreamedTelemetry

#: What telemetry targets cancel: the measured POL values, or the telemetry's own ``s`` (a simulator's truth).
TELEMETRY_TARGETS = ("measured", "s")

#: ``y -> DM(y)`` in nm, on ``(..., K)`` tensors.
DMResponse = Callable[[torch.Tensor], torch.Tensor]


def pol_reconstruction(wfs: torch.Tensor, y: torch.Tensor, dm_response: DMResponse,
                       delay_fraction: float = 0.0) -> torch.Tensor:
    """Pseudo-open-loop turbulence ``s_hat = wfs - DM_model(y)`` (nm), ``(..., frames, K)``; for a fractional delay
    the DM term is the frame's average ``(1 - f) DM_model(y(n)) + f DM_model(y(n-1))``."""
    return wfs - applied_command(dm_response(y), delay_fraction)


def telemetry_targets(wfs: torch.Tensor, y: torch.Tensor, spec: HistorySpec, dm_response: DMResponse,
                      dm_gain: float) -> torch.Tensor:
    """``(..., samples, K)`` targets ``-s_hat(n) / dm_gain`` (fractional delay: ``s_hat`` averaged as in
    :func:`eofnn.data.history.blended_target`) for frames ``first_frame <= n < frames - target_lead``."""
    return -blended_target(pol_reconstruction(wfs, y, dm_response, spec.delay_fraction), spec) / dm_gain


def telemetry_history(wfs: torch.Tensor, y: torch.Tensor, spec: HistorySpec, dm_response: DMResponse) -> torch.Tensor:
    """History tensor of ``spec`` from telemetry: POL values through ``dm_response`` (open loop) or ``y, wfs``."""
    if spec.kind == "open_loop":
        return open_loop_history(pol_reconstruction(wfs, y, dm_response, spec.delay_fraction), spec)
    return build_history(spec, y=y, wfs=wfs)


def telemetry_items(telemetry: AnyTelemetry | Sequence[AnyTelemetry]) -> list[AnyTelemetry]:
    """One or several telemetry files (in memory or streamed) as a list."""
    items = [telemetry] if isinstance(telemetry, (Telemetry, StreamedTelemetry)) else list(telemetry)
    if not items:
        raise TelemetryError("no telemetry given")
    return items


def check_sequences(telemetry: AnyTelemetry | Sequence[AnyTelemetry], spec: HistorySpec | None = None
                    ) -> list[AnyTelemetry]:
    """Independent ``(frames, K)`` sequences of one or several telemetry files, checked to fit ``spec`` (streamed
    files are scanned once, block by block, for non-finite values: :meth:`StreamedTelemetry.check`)."""
    items = telemetry_items(telemetry)
    for item in items:
        if isinstance(item, StreamedTelemetry):
            item.check()
    sequences = [seq for item in items for seq in item.sequences()]
    for seq in sequences:
        if seq.y is None or seq.wfs is None:
            raise TelemetryError("telemetry lacks y or wfs: training and replay from telemetry need both")
    if all(not bool(seq.wfs.any()) and not bool(seq.y.any()) for seq in sequences):
        raise TelemetryError("telemetry holds no signal: y and wfs are zero in every frame (an unconnected "
                             "recording?): nothing can be learnt or replayed from it")
    n_act = {seq.y.shape[-1] for seq in sequences}
    if len(n_act) > 1:
        raise TelemetryError(f"telemetry files disagree on the number of actuators: {sorted(n_act)}")
    delays = {seq.delay_frames for seq in sequences}
    if len(delays) > 1:
        raise TelemetryError(f"telemetry files disagree on delay_frames: {sorted(delays)}")
    if spec is not None:
        if spec.delay_frames != sequences[0].delay_frames:
            raise TelemetryError(f"telemetry has delay_frames={sequences[0].delay_frames} but the history asks for "
                                 f"delay_frames={spec.delay_frames}")
        short = min(seq.y.shape[0] for seq in sequences)
        if short <= spec.first_frame + spec.target_lead:
            raise TelemetryError(f"telemetry has {short} frames: the history (length {spec.history_length}, delay "
                                 f"{spec.delay_frames}) needs more than {spec.first_frame}")
    return sequences


class TelemetryBatches(IterableDataset):
    """Yields ``(history, target)`` batches, ``(samples, K, taps)`` and ``(samples, K)``, from recorded telemetry.

    The telemetry twin of :class:`eofnn.data.stream.SimulatedTelemetry`: histories are built one batch of frames at
    a time (never the whole history tensor), targets through the identified DM (see the module docstring). Each
    batch reads the window of frames ``[start - first_frame, start + batch_frames + target_lead)``: its samples'
    histories reach ``first_frame`` (``history_length + delay - 1``, or more) frames back, so consecutive windows
    overlap by that many frames and a :class:`StreamedTelemetry` reads just these frames from disk. Frames
    ``[first, stop)`` of every sequence are used (``stop=None``: to the end), so a held-out tail can be kept aside.

    Parameters
    ----------
    telemetry : Telemetry or sequence of Telemetry
        Recorded ``y`` and ``wfs`` (several files or batches: independent sequences), in memory or streamed.
    spec : HistorySpec
        History kind, length and delay (the delay must match the telemetry's).
    dm_response : callable
        Identified ``y -> DM(y)`` (nm).
    dm_gain : float
        Identified global DM gain ``g``: targets are ``-s_hat / g``.
    batch_frames : int
        Frames per yielded batch (per sequence).
    first, stop : int
        Frame range used in each sequence.
    target : {"measured", "s"}
        ``"measured"``: the targets cancel the POL values (telemetry alone). ``"s"``: they cancel the telemetry's own
        ``s`` array, ``-s / target_dm_gain``: a simulator's truth recorded beside ``y`` and ``wfs`` (e.g. the DM's
        fit of the true phase, :mod:`eofnn.studies.antialias`), while the histories stay the measured POL values.
    target_dm_gain : float, optional
        The DM gain of ``"s"`` targets (the simulator's own DM; default ``dm_gain``).
    """

    def __init__(self, telemetry: AnyTelemetry | Sequence[AnyTelemetry], spec: HistorySpec, dm_response: DMResponse,
                 dm_gain: float, batch_frames: int = 1024, first: int = 0, stop: int | None = None,
                 target: str = "measured", target_dm_gain: float | None = None) -> None:
        super().__init__()
        self.sequences = check_sequences(telemetry, spec)
        if target not in TELEMETRY_TARGETS:
            raise TelemetryError(f"target={target!r} is invalid: it must be one of {TELEMETRY_TARGETS}")
        if target == "s" and any(getattr(seq, "s", None) is None for seq in self.sequences):
            raise TelemetryError("target='s' needs the telemetry's s array (a simulator's truth), which this "
                                 "telemetry lacks: use target='measured'")
        self.target = target
        self.target_dm_gain = float(dm_gain if target_dm_gain is None else target_dm_gain)
        if not (math.isfinite(self.target_dm_gain) and self.target_dm_gain != 0):
            raise TelemetryError(f"target_dm_gain={target_dm_gain!r} is invalid: it must be finite and non-zero")
        if not (math.isfinite(dm_gain) and dm_gain != 0):
            raise TelemetryError(f"dm_gain={dm_gain!r} is invalid: it must be finite and non-zero")
        if isinstance(batch_frames, bool) or not isinstance(batch_frames, int) or batch_frames < 1:
            raise TelemetryError(f"batch_frames={batch_frames!r} is invalid: it must be an integer >= 1 (frames per "
                                 "batch; each batch also reads the history's first_frame frames before it)")
        self.spec, self.dm_response, self.dm_gain = spec, dm_response, float(dm_gain)
        self.batch_frames, self.first, self.stop = batch_frames, first, stop

    def __iter__(self) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        span, lead = self.spec.first_frame, self.spec.target_lead
        for seq in self.sequences:
            stop = seq.y.shape[0] if self.stop is None else min(self.stop, seq.y.shape[0])
            for start in range(max(self.first, span), stop - lead, self.batch_frames):
                yield self._batch(seq, slice(start - span, min(start + self.batch_frames + lead, stop)))

    def _batch(self, seq, window: slice) -> tuple[torch.Tensor, torch.Tensor]:
        """History and targets of the frames in ``window`` (its window of ``y`` and ``wfs`` is freed on return, so
        the generator holds nothing between batches)."""
        y, wfs = seq.y[window], seq.wfs[window]
        s_hat = pol_reconstruction(wfs, y, self.dm_response, self.spec.delay_fraction)
        # Open loop: the POL values are the history too (computed once; telemetry_history would compute them again).
        history = open_loop_history(s_hat, self.spec) if self.spec.kind == "open_loop" else \
            build_history(self.spec, y=y, wfs=wfs)
        if self.target == "s":
            return history, -blended_target(seq.s[window], self.spec) / self.target_dm_gain
        return history, -blended_target(s_hat, self.spec) / self.dm_gain


def load_telemetry(paths: str | Path | Sequence[str | Path], matrices: dict | None = None, streamed: bool = False
                   ) -> list[AnyTelemetry]:
    """Read one or several telemetry files (``docs/telemetry.md``), each needing ``y`` and ``wfs`` (or ``slopes``);
    ``matrices`` (``interaction_matrix``, ``reconstructor``, ``modal_basis``: arrays or files) apply to every file
    and replace what the files hold. ``streamed``: open them for block reading (:class:`StreamedTelemetry`:
    training and identification then never hold a whole file) instead of reading them whole."""
    paths = [paths] if isinstance(paths, (str, Path)) else list(paths)
    if not paths:
        raise TelemetryError("no telemetry file given")
    space = {name: read_matrix(value, name) if isinstance(value, (str, Path)) else value
             for name, value in (matrices or {}).items() if value is not None}
    return [_open(path, space) if streamed else _whole(path, space) for path in paths]


def in_nm(telemetry: AnyTelemetry, command_unit="surface", measurement_unit=None,
          mechanical_coupling: float | None = None) -> tuple[AnyTelemetry, str]:
    """``telemetry`` with ``y`` in nm (from ``command_unit``) and ``wfs`` (and ``s``, ``eps``) in nm (from
    ``measurement_unit``, default the commands' unit) (:mod:`eofnn.telemetry.units`; ``peak`` at
    ``mechanical_coupling``, default OOPAO's), and one line saying what was converted ("" when nothing was)."""
    peak = surface_per_command(MECHANICAL_COUPLING if mechanical_coupling is None else mechanical_coupling)
    command, measurement, note = conversion(command_unit, measurement_unit, peak)
    if not note:
        return telemetry, ""
    if isinstance(telemetry, StreamedTelemetry):
        return telemetry.scaled(command, measurement), note
    return replace(telemetry, y=telemetry.y * command, **{name: getattr(telemetry, name) * measurement
                                                          for name in ("wfs", "s", "eps")
                                                          if getattr(telemetry, name) is not None}), note


def _whole(path, space: dict) -> Telemetry:
    """The file in memory, refused up front when its float64 arrays (and the read buffers converting them) would
    not fit (the header says how big they are)."""
    try:
        header = StreamedTelemetry.open(path, space=space)
    except TelemetryError:
        header = None  # Telemetry.load says what is wrong, or reads what cannot be read in blocks
    if header is not None:
        values = sum(math.prod(array.shape) for array in (header.y, header.wfs))
        require_memory(3 * 8 * values, f"reading telemetry file {str(path)!r} whole ({values} values)")
    return Telemetry.load(path, required=TELEMETRY_REQUIRED, space=space)


def _open(path, space: dict) -> AnyTelemetry:
    """A file for block reading; one whose frames are not contiguous on disk (Fortran order, compressed images) is
    read whole, as before streaming existed."""
    try:
        return StreamedTelemetry.open(path, space=space)
    except NotStreamableError:
        return Telemetry.load(path, required=TELEMETRY_REQUIRED, space=space)


def telemetry_grid(telemetry: AnyTelemetry, grid: ActuatorGrid | ActuatorLayout | None = None
                   ) -> ActuatorGrid | ActuatorLayout | None:
    """The actuator layout of ``telemetry``: ``grid`` if given, else None for modal telemetry, else its positions
    (eofnn's own grid when they are one, else an :class:`~eofnn.sim.layout.ActuatorLayout`), else its eofnn
    scenario's grid, else None."""
    if grid is not None:
        return grid
    if telemetry.modal_basis is not None:  # predictors run in modes: no actuator neighbourhoods, no shift model
        return None
    if telemetry.positions_m is not None:
        return layout_from_positions(telemetry.positions_m)
    scenario = telemetry.config.get("scenario") or telemetry.config.get("eofnn", {}).get("scenario")
    if isinstance(scenario, dict) and isinstance(scenario.get("grid"), dict):
        return layout_from_dict(scenario["grid"])
    return None
