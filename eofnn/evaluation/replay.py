"""Replay: a predictor's offline prediction error on held-out telemetry, as on-sky teams evaluate before deploying.

For each frame ``n`` the predictor computes the command ``y_pred(n)`` from the history that was available at ``n``
(``y`` and ``wfs`` as recorded); the telemetry later shows what was needed: ``y_need(n) = -s_hat(n) / g`` with the
POL reconstruction ``s_hat(n) = wfs(n) - DM_model(y(n))`` and the identified (or given) global gain ``g``: the
training target of :mod:`eofnn.data.targets`. The error is reported on the wavefront, ``e(n) = g (y_pred(n) -
y_need(n)) = g y_pred(n) + s_hat(n)`` in nm, beside the error the telemetry's own controller really left, the
measured residual ``wfs(n)`` (``= g y(n) + s_hat(n)`` for a DM that is a pure gain). For a fractional delay
``d + f`` each ``y`` in these is the frame's average ``(1 - f) y(n) + f y(n - 1)`` (recorded and predicted alike).

What is comparable with a closed-loop run: for a DM that is a pure gain, ``e(n)`` is ``eps(n) = s(n) + g y(n)`` of
a loop driven by the predictor, plus the WFS noise ``v(n)`` that ``s_hat(n)`` carries (the true residual does not):
the raw RMS and the RMS with the (identified or given) noise variance removed in quadrature are both reported. The
histories come from the recording controller's loop, not the predictor's: for an open-loop (POL) predictor that
does not matter when the DM model is right; a closed-loop predictor is replayed faithfully only on telemetry it
recorded itself (with dither), since its history includes its own commands. Under misregistration the loop residual
also holds the shape the DM cannot apply and what feedback does about it, which the replay does not see.

Modal telemetry (``modal_basis`` ``B``): the predictor runs in modes and both errors are mapped to the actuators,
``B @ e`` (nm per actuator), before the statistics; the noise correction removes the identified per-mode noise as
if it were per actuator (right for a square orthonormal basis, approximate otherwise).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch import nn

from eofnn.data.history import HistorySpec, applied_command
from eofnn.data.targets import (
    AnyTelemetry,
    check_sequences,
    pol_reconstruction,
    telemetry_grid,
    telemetry_history,
    telemetry_items,
)
from eofnn.errors import ConfigError
from eofnn.evaluation.metrics import WelchPSD
from eofnn.outputs import check_output_file, write_text_atomic
from eofnn.sim.grid import ActuatorGrid
from eofnn.telemetry.spaces import modal_to_actuators
from eofnn.training.from_telemetry import resolve_plant
from eofnn.training.identify import IdentifiedPlant


@dataclass
class ErrorStats:
    """One controller's replayed error (nm): RMS per frame, its median/mean, map per actuator, temporal PSD."""

    median_rms_nm: float
    mean_rms_nm: float
    median_rms_noise_corrected_nm: float | None
    rms_nm: list[float] = field(repr=False)
    map_rms_nm: list[float] = field(repr=False)
    psd_nm2_per_hz: list[float] = field(repr=False)
    #: What the noise-corrected value is, or why it could not be estimated (then it is ``None``).
    noise_correction: str = ""


@dataclass
class ReplayResult:
    """Outcome of :func:`replay` (``replay.json``): the predictor's error beside the telemetry's own controller's."""

    predictor: ErrorStats
    own_controller: ErrorStats
    noise_nm: float
    n_frames: int
    first_frame: int
    frame_rate_hz: float
    psd_freq_hz: list[float] = field(repr=False)
    plant: dict = field(default_factory=dict)
    #: One line per condition (WFS noise, DM gain) in which the telemetry differs from the predictor's training
    #: (:mod:`eofnn.training.conditions`); empty when none does, or when either is unknown.
    shift: list[str] = field(default_factory=list)
    #: The guard's decision (:func:`eofnn.evaluation.fallback.decide_on_telemetry`): the predictor or the own controller.
    guard: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """The JSON-ready scalars."""
        pick = ("median_rms_nm", "mean_rms_nm", "median_rms_noise_corrected_nm", "noise_correction")
        return {"predictor": {k: getattr(self.predictor, k) for k in pick},
                "own_controller": {k: getattr(self.own_controller, k) for k in pick},
                "noise_nm": self.noise_nm, "n_frames": self.n_frames, "plant": self.plant, "shift": self.shift,
                "guard": self.guard}

    def to_json(self, path: str | Path | None = None, overwrite: bool = False) -> str:
        text = json.dumps(asdict(self), indent=1)
        if path is not None:
            write_text_atomic(check_output_file(path, overwrite), text)
        return text


class _ErrorAccumulator:
    """One controller's replayed error, block by block of frames: the RMS of each frame, the sum of squares of each
    actuator and the temporal PSD; nothing of the error itself is kept."""

    def __init__(self, psd: WelchPSD) -> None:
        self.psd, self.rms2, self.sum2, self.frames = psd, [], None, 0

    def add(self, error: torch.Tensor) -> None:
        """``(frames, K)`` errors (nm) of consecutive frames."""
        squared = error.pow(2)
        self.rms2.append(squared.mean(-1))
        self.sum2 = squared.sum(0) if self.sum2 is None else self.sum2 + squared.sum(0)
        self.frames += error.shape[0]
        self.psd(0, {"eps": error.unsqueeze(0)})

    def stats(self, noise_nm: float) -> ErrorStats:
        rms = torch.cat(self.rms2).sqrt()
        per_actuator = (self.sum2 / self.frames).sqrt()
        median = float(rms.median())
        if noise_nm <= 0:
            corrected, note = median, "no WFS noise estimate (plant not identified): equal to the raw median RMS"
        elif median <= noise_nm:
            # Removing more noise than the error holds would print 0 nm, which no predictor reaches: say so instead.
            corrected, note = None, (f"cannot be estimated: the median RMS ({median:.3g} nm) is within the WFS noise "
                                     f"({noise_nm:.3g} nm) that the POL values carry")
        else:
            corrected = float((rms.pow(2) - noise_nm ** 2).clamp(min=0).sqrt().median())
            note = f"median RMS with {noise_nm:.3g} nm of WFS noise removed in quadrature"
        return ErrorStats(median, float(rms.mean()), corrected, rms.tolist(), per_actuator.tolist(),
                          self.psd.result()[1], note)


#: History elements (frames x actuators x taps) a replayed network reads at once.
REPLAY_BLOCK_ELEMENTS = 2**23


@torch.no_grad()
def replay(network: nn.Module, spec: HistorySpec, telemetry: AnyTelemetry | Sequence[AnyTelemetry], *,
           plant: IdentifiedPlant | dict | None = None, noise_nm: float | None = None, grid: ActuatorGrid | None = None,
           start: int = 0, settle_frames: int = 0, segment_frames: int = 256,
           frame_rate_hz: float | None = None, guard_blocks: int = 8, guard_sigmas: float = 2.0) -> ReplayResult:
    """Replay ``network`` (reading ``spec`` histories) on recorded telemetry.

    Parameters
    ----------
    network : nn.Module
        Maps ``(batch, K, spec.n_taps)`` histories to commands (nm).
    spec : HistorySpec
        The history it reads (delay must be the telemetry's).
    telemetry : Telemetry, StreamedTelemetry or a sequence of them
        Held-out ``y`` and ``wfs``; read in blocks of frames (each with the history before it), so a file is never
        held whole: memory is set by :data:`REPLAY_BLOCK_ELEMENTS`.
    plant : IdentifiedPlant, dict or None
        DM model for the POL reconstruction (see :func:`eofnn.training.from_telemetry.resolve_plant`).
    noise_nm : float, optional
        WFS noise removed in quadrature from the corrected RMS; default the identified plant's, else 0.
    start : int
        First frame of each sequence to replay (frames before it are history only).
    settle_frames : int
        Frames after the first predictable one left out of the statistics.
    segment_frames : int
        Welch segment length of the PSD.
    frame_rate_hz : float, optional
        For the PSD axis; default the telemetry's, else 1000.
    guard_blocks, guard_sigmas : int, float
        The guard's blocks and standard errors (:func:`eofnn.evaluation.fallback.decide_on_telemetry`).
    """
    sequences = check_sequences(telemetry, spec)
    first_item = telemetry_items(telemetry)[0]
    dm_response, dm_gain, errors, source = resolve_plant(plant, spec.delay_frames, telemetry_grid(first_item, grid))
    if noise_nm is None:
        noise_nm = float(plant.wfs_noise_nm or 0.0) if isinstance(plant, IdentifiedPlant) else 0.0
    rate = frame_rate_hz or first_item.frame_rate_hz or 1000.0
    first = max(start, spec.first_frame) + settle_frames
    if any(seq.y.shape[0] <= first for seq in sequences):
        raise ConfigError(f"start={start}, settle_frames={settle_frames}: the telemetry has no frame left to replay")
    params = list(network.parameters())
    dtype = params[0].dtype if params else torch.float64
    network.eval()
    f, span = spec.delay_fraction, spec.first_frame
    lengths = [seq.y.shape[0] - first - spec.target_lead - (1 if f else 0) for seq in sequences]  # per sequence
    segment = min(segment_frames, *lengths)
    predicted, own = _ErrorAccumulator(WelchPSD(segment, rate)), _ErrorAccumulator(WelchPSD(segment, rate))
    # In blocks of frames, each read with the history before it: a file is never held whole, and a neighbourhood
    # filter gathers (frames, K, M x taps) at once (2000 frames of 5024 actuators, 9 neighbours, 10 taps in one
    # call: 7.2 GB of float64 before any temporary; the peak measured: docs/findings.md).
    block = max(1, REPLAY_BLOCK_ELEMENTS // max(1, sequences[0].y.shape[-1] * spec.n_taps))
    for seq in sequences:
        for begin in range(first, seq.y.shape[0], block):
            # A fractional delay's DM shape over frame n averages the commands of frames n and n - 1: a block after
            # the first also predicts the frame before it (the first block's first frame has no predecessor).
            extra = 1 if f and begin > first else 0
            # The window ends target_lead frames after the block: a fractional delay's history reads one frame on.
            window = slice(begin - span - extra, min(begin + block + spec.target_lead, seq.y.shape[0]))
            y, wfs = seq.y[window], seq.wfs[window]
            y_pred = network(telemetry_history(wfs, y, spec, dm_response).to(dtype)).to(torch.float64)
            s_hat = pol_reconstruction(wfs, y, dm_response, f)[span:][:len(y_pred)]
            measured = wfs[span:][:len(y_pred)]
            if f:
                y_pred, s_hat, measured = applied_command(y_pred, f)[1:], s_hat[1:], measured[1:]
            error = s_hat + dm_gain * y_pred
            if seq.modal_basis is not None:  # modal telemetry: errors are reported on the actuators, B @ e
                error = modal_to_actuators(error, seq.modal_basis)
                measured = modal_to_actuators(measured, seq.modal_basis)
            predicted.add(error)
            own.add(measured)
    result = ReplayResult(predicted.stats(noise_nm), own.stats(noise_nm), noise_nm, predicted.frames, first, rate,
                          predicted.psd.result()[0], {"source": source, "dm_gain": dm_gain, **errors})
    from eofnn.evaluation.fallback import decide_on_telemetry  # the fallback's statistic, on the record

    result.guard = decide_on_telemetry(result.predictor.rms_nm, result.own_controller.rms_nm, guard_blocks,
                                       guard_sigmas)
    return result
