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
from eofnn.data.targets import check_sequences, pol_reconstruction, telemetry_grid, telemetry_history
from eofnn.errors import ConfigError
from eofnn.evaluation.metrics import WelchPSD
from eofnn.outputs import check_output_file, write_text_atomic
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.spaces import modal_to_actuators
from eofnn.sim.telemetry import Telemetry
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

    def summary(self) -> dict:
        """The JSON-ready scalars."""
        pick = ("median_rms_nm", "mean_rms_nm", "median_rms_noise_corrected_nm", "noise_correction")
        return {"predictor": {k: getattr(self.predictor, k) for k in pick},
                "own_controller": {k: getattr(self.own_controller, k) for k in pick},
                "noise_nm": self.noise_nm, "n_frames": self.n_frames, "plant": self.plant}

    def to_json(self, path: str | Path | None = None, overwrite: bool = False) -> str:
        text = json.dumps(asdict(self), indent=1)
        if path is not None:
            write_text_atomic(check_output_file(path, overwrite), text)
        return text


def _stats(error: list[torch.Tensor], noise_nm: float, psd: WelchPSD) -> ErrorStats:
    rms = torch.cat([e.pow(2).mean(-1) for e in error]).sqrt()
    per_actuator = torch.cat(error).pow(2).mean(0).sqrt()
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
    for e in error:
        psd(0, {"eps": e.unsqueeze(0)})
    return ErrorStats(median, float(rms.mean()), corrected, rms.tolist(), per_actuator.tolist(), psd.result()[1],
                      note)


#: History elements (frames x actuators x taps) a replayed network reads at once.
REPLAY_BLOCK_ELEMENTS = 2**23


@torch.no_grad()
def replay(network: nn.Module, spec: HistorySpec, telemetry: Telemetry | Sequence[Telemetry], *,
           plant: IdentifiedPlant | dict | None = None, noise_nm: float | None = None, grid: ActuatorGrid | None = None,
           start: int = 0, settle_frames: int = 0, segment_frames: int = 256,
           frame_rate_hz: float | None = None) -> ReplayResult:
    """Replay ``network`` (reading ``spec`` histories) on recorded telemetry.

    Parameters
    ----------
    network : nn.Module
        Maps ``(batch, K, spec.n_taps)`` histories to commands (nm).
    spec : HistorySpec
        The history it reads (delay must be the telemetry's).
    telemetry : Telemetry or sequence of Telemetry
        Held-out ``y`` and ``wfs``.
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
    """
    sequences = check_sequences(telemetry, spec)
    first_item = telemetry if isinstance(telemetry, Telemetry) else telemetry[0]
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
    predicted, own, f = [], [], spec.delay_fraction
    for seq in sequences:
        window = slice(first - spec.first_frame, None)
        y, wfs = seq.y[window], seq.wfs[window]
        history = telemetry_history(wfs, y, spec, dm_response)
        # In blocks of frames: a neighbourhood filter gathers (frames, K, M x taps) at once, and replaying 2000
        # frames of 5024 actuators (9 neighbours, 10 taps) in one call peaked at 15.8 GB.
        block = max(1, REPLAY_BLOCK_ELEMENTS // max(1, history[0].numel()))
        y_pred = torch.cat([network(history[a: a + block].to(dtype)).to(torch.float64)
                            for a in range(0, len(history), block)])
        s_hat = pol_reconstruction(wfs, y, dm_response, f)[spec.first_frame:][:len(y_pred)]
        measured = wfs[spec.first_frame:][:len(y_pred)]
        if f:  # the DM shape over frame n averages the predicted commands of frames n and n - 1
            y_pred, s_hat, measured = applied_command(y_pred, f)[1:], s_hat[1:], measured[1:]
        error = s_hat + dm_gain * y_pred
        if seq.modal_basis is not None:  # modal telemetry: errors are reported on the actuators, B @ e
            error, measured = modal_to_actuators(error, seq.modal_basis), modal_to_actuators(measured, seq.modal_basis)
        predicted.append(error)
        own.append(measured)
    segment = min(segment_frames, min(e.shape[0] for e in predicted))
    psd_pred, psd_own = WelchPSD(segment, rate), WelchPSD(segment, rate)
    result = ReplayResult(_stats(predicted, noise_nm, psd_pred), _stats(own, noise_nm, psd_own), noise_nm,
                          sum(e.shape[0] for e in predicted), first, rate, psd_pred.result()[0],
                          {"source": source, "dm_gain": dm_gain, **errors})
    return result
