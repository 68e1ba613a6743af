"""Per-mode gains identified from closed-loop telemetry with a modal dither: a pyramid's optical gains on sky.

The plant identification (:mod:`eofnn.training.identify`) measures the response of each actuator's measurement to
the dither; a pyramid's response is not one gain but one per mode (its optical gains,
:mod:`eofnn.sim.sensing.optical_gains`), lowered about the loop's residual. Here the same two regressions run on
the telemetry projected on the orthonormal Karhunen-Loeve command modes ``M`` (:func:`~eofnn.sim.sensing.
optical_gains.kl_modes`): ``a(n) = M^T y(n)``, ``b(n) = M^T wfs(n)`` for the requested modes. Per mode ``m``,

1. *whitening*: ``Da_m(n) = a_m(n) - a_m(n-1)`` regressed on ``z_m(n) = [a_m(n-2..n-p-1), b_m(n-2..n-p-1)]``; for
   an integrator with a delay of at least 2 frames the residual is ``u_m(n) = w_m(n) - w_m(n-1)``, the increment of
   the dither's mode ``m`` (the loop's own transfer, the controller acting on past residuals, is what the fit
   removes);
2. *response*: ``Db_m(n)`` regressed on ``u_m(n)`` and ``z_m(n)``: the coefficient on ``u_m`` is the response of
   mode ``m``'s measurement to mode ``m``'s command, ``g_dm * og_m`` (a DM gain and an optical gain are not
   separable from telemetry, as in :mod:`eofnn.training.identify`), its standard error from the residual variance
   and the inverse Gram matrix.

The dither may be white on every actuator (every mode is then excited, as weakly as the per-actuator dither) or
white on a few KL modes (``Dithered(..., modes=...)``): a mode whose whitened innovation is numerical residue is
refused as undithered, and one whose gain is known to worse than :data:`MAX_RELATIVE_SE` of itself as too weakly
dithered. The gains are the linear response at the loop's operating point, averaged over the record: those the
probe :func:`~eofnn.sim.sensing.optical_gains.modal_optical_gains` measures about the same residual. Cross-talk
between modes (a pyramid's response to mode ``j`` seen in mode ``m``) is not fitted: the other modes' dither is
independent of ``u_m`` and only adds to the error.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from eofnn.data.targets import AnyTelemetry, check_sequences, telemetry_grid, telemetry_items
from eofnn.errors import TelemetryError, require
from eofnn.sim.sensing.optical_gains import kl_modes
from eofnn.training.identify import _batches, _innovation, _realigned, _Regressors, _solve, _whiten
from eofnn.training.ridge import NormalEquations

__all__ = ["MAX_RELATIVE_SE", "identify_modal_gains"]

#: Largest standard error of an identified gain, relative to the gain, before its mode's dither counts as too weak.
MAX_RELATIVE_SE = 0.1
#: Below this ratio of whitened to raw command-increment RMS in a mode, the mode counts as undithered.
MIN_EXCITATION = 1e-6


class _Projected:
    """``(frames, M)`` view of a ``(frames, K)`` array projected on ``(K, M)`` modes, read a block at a time."""

    def __init__(self, array, modes: torch.Tensor) -> None:
        self.array, self.modes = array, modes
        self.shape = (array.shape[0], modes.shape[1])

    def __getitem__(self, index) -> torch.Tensor:
        return torch.as_tensor(self.array[index]).to(torch.float64) @ self.modes


class _ModalSequence:
    """A sequence's ``y`` and ``wfs`` projected on modes, ``wfs`` realigned by ``lag`` frames first."""

    def __init__(self, seq, modes: torch.Tensor, lag: int) -> None:
        seq = seq if lag == 0 else _realigned(seq, lag)
        self.y, self.wfs = _Projected(seq.y, modes), _Projected(seq.wfs, modes)


def identify_modal_gains(telemetry: AnyTelemetry | Sequence[AnyTelemetry], orders: Sequence[int], grid=None, *,
                         lag_frames: int = 0, nuisance_lags: int = 2, batch_frames: int = 1024) -> dict:
    """Per-mode gains (the DM gain times the sensor's optical gain) of the Karhunen-Loeve command modes of 1-based
    ``orders`` from dithered closed-loop telemetry (method: module docstring).

    Returns ``{"basis", "orders", "gains", "gains_se", "excitation_rms_nm", "mean_gain", "nuisance_lags"}``:
    ``excitation_rms_nm`` the RMS per frame of each mode's dither as the whitening recovers it. ``lag_frames``: the
    WFS lag :func:`~eofnn.training.identify.identify_plant` found (``wfs`` is realigned by it). One-line
    :class:`TelemetryError` for telemetry without positions, a mode without dither or one dithered too weakly.
    """
    sequences = check_sequences(telemetry)
    first_item = telemetry_items(telemetry)[0]
    grid = telemetry_grid(first_item, grid)
    if grid is None:
        raise TelemetryError("optical gains need actuator-space telemetry with positions (positions_m or an eofnn "
                             "scenario): the Karhunen-Loeve modes are built on the actuators")
    n_act = grid.n_actuators
    orders = list(orders)
    require(len(orders) > 0 and all(isinstance(o, int) and not isinstance(o, bool) and 1 <= o < n_act
                                    for o in orders) and len(set(orders)) == len(orders),
            f"optical_gain_modes={orders!r} is invalid: it must be distinct Karhunen-Loeve mode orders from 1 to "
            f"{n_act - 1} (1: the first mode after piston)")
    p, first = nuisance_lags, nuisance_lags + 2
    short = min(seq.y.shape[0] for seq in sequences) - lag_frames
    if short < first + 200:
        raise TelemetryError(f"telemetry has {short} frames: optical-gain identification needs at least {first + 200}")
    modes = torch.as_tensor(kl_modes(grid, max(orders))[:, [o - 1 for o in orders]], dtype=torch.float64)
    modal = [_ModalSequence(seq, modes, lag_frames) for seq in sequences]
    beta = _whiten(modal, p, first, batch_frames)
    n_modes = len(orders)
    power, raw = torch.zeros(n_modes, dtype=torch.float64), torch.zeros(n_modes, dtype=torch.float64)
    regression, count = NormalEquations(), 0
    whitening, regressors = _Regressors(n_modes, 2 * p, batch_frames), _Regressors(n_modes, 1 + 2 * p, batch_frames)
    for _, a, b, o, y, wfs in _batches(modal, p, first, batch_frames):
        u = _innovation(beta, whitening, y, wfs, p, a - o, b - o)
        power += u.pow(2).sum(-1)
        raw += (y[:, a - o: b - o] - y[:, a - o - 1: b - o - 1]).pow(2).sum(-1)
        count += b - a
        features = regressors.nuisance(y, wfs, p, a - o, b - o, offset=1)
        features[:, 0].copy_(u)
        regression.update(features.transpose(1, 2), wfs[:, a - o: b - o] - wfs[:, a - o - 1: b - o - 1])
    undithered = [o for o, pw, r in zip(orders, power, raw, strict=True) if pw <= MIN_EXCITATION ** 2 * r]
    if undithered:
        raise TelemetryError(f"optical_gain_modes {undithered} carry no dither in this telemetry (their commands are a "
                             "function of the past residuals): record with a dither on those Karhunen-Loeve modes, "
                             "or ask for dithered modes only")
    weights = _solve(regression)
    gram = regression.gram
    sse = regression.target_power - 2 * (weights * regression.cross).sum(-1) + (
        weights.unsqueeze(1) @ gram @ weights.unsqueeze(-1)).view(-1)
    variance = sse.clamp(min=0) / (regression.n_samples - gram.shape[-1])
    se = (variance * torch.linalg.pinv(gram, hermitian=True)[:, 0, 0]).clamp(min=0).sqrt()
    gains = weights[:, 0]
    excitation = (power / 2 / count).sqrt()  # u = w(n) - w(n-1): twice the dither's variance
    weak = [f"{o} (gain {float(g):.3g} +- {float(s):.2g}, dither {float(e):.2g} nm RMS)"
            for o, g, s, e in zip(orders, gains, se, excitation, strict=True) if s > MAX_RELATIVE_SE * abs(g)]
    if weak:
        raise TelemetryError(f"optical_gain_modes dithered too weakly for the noise and length of this telemetry: "
                             f"{'; '.join(weak)}; the standard error must be below {MAX_RELATIVE_SE:.0%} of the gain: "
                             "record longer or with a larger dither on those modes")
    return {"basis": "karhunen_loeve", "orders": orders, "gains": gains.tolist(), "gains_se": se.tolist(),
            "excitation_rms_nm": excitation.tolist(), "mean_gain": float(gains.mean()),
            "mean_gain_se": float(se.pow(2).sum().sqrt()) / n_modes, "nuisance_lags": p,
            "n_frames": int(count)}

