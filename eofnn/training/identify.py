"""Plant identification from dithered closed-loop telemetry: the interaction matrix measured on sky.

The data controller adds white dither ``w(n)`` to its commands, ``y(n) = C(n) + w(n)``, where ``C(n)`` is what the
controller computed from the past (an integrator, a predictor). The WFS reports

    wfs_k(n) = sum_j G_kj y_j(n) + s_k(n) + v_k(n)

with ``G`` the DM response (gain, misregistration: a sparse matrix over each actuator's neighbourhood),
``s`` the turbulence and ``v`` white WFS noise. Regressing ``wfs(n)`` on ``y(n)`` directly is biased: ``C(n)`` is
built from past residuals, which are correlated with ``s(n)``. The dither is the one part of ``y`` that is
independent of the turbulence, so the estimate is built on it. Levels do not work for the usual data controller:
an integrator's state ``C(n) = y(n-1) - w(n-1) - k wfs(n-d)`` involves the unobserved ``w(n-1)`` and, unrolled,
the whole past, so a finite regression of ``y(n)`` on its past leaves a remainder of past dither that the projection
mixes with turbulence (a gain bias: ``docs/findings.md``). *Increments* do: ``Dy(n) = y(n) - y(n-1)
= -k wfs(n-d) + w(n) - w(n-1)`` has finite memory. Two regressions (streamed normal equations), with the nuisance
regressors ``z_j(n) = [y_j(n-2..n-p-1), wfs_j(n-2..n-p-1)]`` (``p = nuisance_lags``), which hold no ``w(n)`` or
``w(n-1)`` when the delay is at least 2 frames:

1. *Whitening.* Per actuator, regress ``Dy_j(n)`` on ``z_j(n)``. For an integrator the fit is ``-k wfs_j(n-d)``
   exactly and the residual is ``u_j(n) = w_j(n) - w_j(n-1)``: independent of the turbulence, the noise, the
   nuisance regressors and the other actuators' dither.
2. *Response.* Per actuator ``k``, regress ``Dwfs_k(n) = wfs_k(n) - wfs_k(n-1)`` on ``u_j(n)`` for the neighbours
   ``j`` of ``k`` and on ``z_k(n)`` (the residual's own past, which absorbs the controller's and much of the
   turbulence's part and so shrinks the error). ``Dwfs_k(n) = sum_j G_kj (u_j(n) + fit_j(n)) + Ds_k + Dv_k`` and
   every term but ``G_kj u_j(n)`` is independent of ``u_j(n)``, so the coefficient on ``u_j(n)`` is ``G_kj``
   (Frisch-Waugh-Lovell). Standard errors come from the residual variance and the inverse Gram matrix.

The method is exact for (leak-free) integrators with delay >= 2 frames, the data controller of eofnn and of most
AO systems; a controller with more memory (a leaky integrator, a predictor recording refit data) leaves a small
remainder of past dither in ``u``; raising ``nuisance_lags`` to its history length shrinks it.

From the coupling rows ``G_k.``: per-actuator gains (row sums), and, pooled over actuators whose neighbourhood is
complete, the global gain ``g = sum P`` and the misregistration of a bilinear shift as
:func:`eofnn.sim.loop.plant._shift_operator` applies it, whose weights ``tri(a + dy) tri(b + dx)`` have first moments
``dx = -sum_b b P / g``, ``dy = -sum_a a P / g`` (exact for shifts within the neighbourhood; standard errors by
the delta method, taking actuators as independent). The WFS lag is where the pooled response of ``Dwfs(n + l)``
to ``u(n)`` peaks over ``l = 0..max_lag``: 0 in the documented convention (``wfs(n)`` measures ``eps(n)``); a file
whose ``wfs`` is recorded ``L`` frames later is realigned and identified again.

The WFS noise: the POL reconstruction ``s_hat = wfs - DM_model(y) = s + v`` has structure function
``D(l) = D_s(l) + 2 sigma_v**2`` for lags ``l >= 1``; smooth turbulence has an even ``D_s(l) = c l**2 + O(l**4)``,
so ``(4 D(1) - D(2)) / 3 = 2 sigma_v**2`` (the autocovariance extrapolation to lag 0 used on AO telemetry).

What telemetry cannot separate: a DM gain from a WFS optical gain (only their product ``g`` is seen: it is the
product that POL reconstruction needs); a DM from a WFS misregistration (only the relative one); white noise from
turbulence that is not smooth over three frames (it biases the noise estimate up); temporally correlated noise
from turbulence (it is counted as turbulence); a DM nonlinearity (the fit is the linear response at the operating
point). Without dither ``w_hat`` vanishes and nothing can be identified: the result says so.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import torch

from eofnn.data.targets import AnyTelemetry, check_sequences, telemetry_grid, telemetry_items
from eofnn.errors import CollinearityWarning, TelemetryError, require
from eofnn.resources import require_memory
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.layout import ActuatorLayout, coupling_stencils, layout_to_dict
from eofnn.telemetry.file import StreamedTelemetry
from eofnn.telemetry.record import Telemetry
from eofnn.training.identified import IdentifiedPlant, PlantNotIdentifiedWarning
from eofnn.training.ridge import NormalEquations

__all__ = ["IdentifiedPlant", "PlantNotIdentifiedWarning", "identify_plant"]


class _Regressors:
    """A ``(K, features, batch_frames)`` buffer, allocated once, that each batch's regressors are copied into.

    Regressors are laid out ``(groups, features, samples)``, samples contiguous: the normal equations get them as
    a transposed view, so the Gram products run on contiguous rows without a copy; filling the buffer in place
    (rather than stacking and concatenating fresh tensors per batch) halves the memory traffic of a batch.
    """

    def __init__(self, n_groups: int, n_features: int, batch_frames: int) -> None:
        self.buffer = torch.empty(n_groups, n_features, batch_frames, dtype=torch.float64)

    def nuisance(self, y: torch.Tensor, wfs: torch.Tensor, p: int, a: int, b: int, offset: int = 0) -> torch.Tensor:
        """Rows ``offset ..`` get ``z(n) = [y(n-2..n-p-1), wfs(n-2..n-p-1)]``, the past that holds neither ``w(n)``
        nor ``w(n-1)``; returns the filled ``(K, offset + 2p, b - a)`` view."""
        out = self.buffer[..., : b - a]
        for i, lag in enumerate(range(2, p + 2)):
            out[:, offset + i].copy_(y[:, a - lag: b - lag])
            out[:, offset + p + i].copy_(wfs[:, a - lag: b - lag])
        return out[:, : offset + 2 * p]


def _chunks(start: int, stop: int, size: int):
    for first in range(start, stop, size):
        yield first, min(first + size, stop)


def _solve(ne: NormalEquations) -> torch.Tensor:
    with warnings.catch_warnings():  # collinearity without dither is reported by identify_plant itself
        warnings.simplefilter("ignore", CollinearityWarning)
        return ne.solve(0.0, relative=False).weights


def identify_plant(telemetry: AnyTelemetry | Sequence[AnyTelemetry], grid: ActuatorGrid | ActuatorLayout | None = None, *,
                   radius: float = 1.5, nuisance_lags: int = 2, max_lag: int | None = None, batch_frames: int = 1024,
                   min_excitation: float = 1e-6) -> IdentifiedPlant:
    """Identify DM response, WFS lag and noise from dithered closed-loop telemetry (method: module docstring).

    Parameters
    ----------
    telemetry : Telemetry, StreamedTelemetry or a sequence of them
        Recorded ``y`` and ``wfs`` (nm); several files or batches are independent sequences of one plant. Every
        pass (whitening, excitation and lag, response, noise) reads ``batch_frames`` frames at a time plus the
        lags it needs, so a :class:`~eofnn.telemetry.file.StreamedTelemetry` is never held whole.
    grid : ActuatorGrid or ActuatorLayout, optional
        The actuator layout; by default from the telemetry's ``positions_m`` or its eofnn scenario. Without one the
        DM gain and the lag are still identified (from each actuator's response to its own dither), the
        misregistration is not (no shift model without positions).
    radius : float
        Neighbourhood radius in pitches over which coupling is fitted (1.5: the 3 x 3 neighbours on a square
        lattice, the 6 nearest on a hexagonal one; enough for misregistrations below one pitch).
    nuisance_lags : int
        ``p``: frames ``n-2 .. n-p-1`` of ``y`` and ``wfs`` in the nuisance regressors; must reach the data
        controller's input ``wfs(n - delay)`` (``p >= delay - 1``).
    max_lag : int, optional
        Largest WFS lag searched, in frames (default ``delay_frames + 2``).
    batch_frames : int
        Frames per streamed batch.
    min_excitation : float
        Below this ratio of whitened to raw command-increment RMS, the telemetry counts as undithered.
    """
    sequences = check_sequences(telemetry)
    first_item = telemetry_items(telemetry)[0]
    grid = telemetry_grid(first_item, grid)
    n_act, delay = sequences[0].y.shape[-1], sequences[0].delay_frames
    if not float(delay).is_integer():  # the lag search and the whitening assume whole frames
        raise TelemetryError(f"telemetry has delay_frames={delay}: plant identification supports integer delays "
                             "only (give the plant instead, e.g. fit --plant plant.json)")
    if grid is not None and grid.n_actuators != n_act:
        raise TelemetryError(f"telemetry has {n_act} actuators but the grid has {grid.n_actuators}")
    require(isinstance(nuisance_lags, int) and nuisance_lags >= max(1, delay - 1),
            f"nuisance_lags={nuisance_lags!r} is invalid: it must be an integer >= max(1, delay_frames - 1) = "
            f"{max(1, delay - 1)}")
    require(isinstance(batch_frames, int) and not isinstance(batch_frames, bool) and batch_frames >= 1,
            f"batch_frames={batch_frames!r} is invalid: it must be an integer >= 1 (frames per pass step)")
    max_lag = delay + 2 if max_lag is None else max_lag
    require(isinstance(max_lag, int) and max_lag >= 0, f"max_lag={max_lag!r} is invalid: it must be an integer >= 0")
    settings = {"radius": radius, "nuisance_lags": nuisance_lags, "max_lag": max_lag, "batch_frames": batch_frames}
    first = nuisance_lags + 1 + max_lag
    short = min(seq.y.shape[0] for seq in sequences)
    if short < first + 200:
        raise TelemetryError(f"telemetry has {short} frames: identification needs at least {first + 200}")
    result = IdentifiedPlant(False, delay, {} if grid is None else layout_to_dict(grid),
                             n_frames=sum(seq.y.shape[0] for seq in sequences), n_sequences=len(sequences),
                             settings=settings)
    if delay < 2:
        result.warnings.append("delay_frames=1: the controller's input wfs(n-1) holds the previous dither, so the "
                               "whitening is not exact; identified values may be biased")
    require_memory(identify_working_bytes(n_act, 1 if grid is None else grid.neighbours(radius).shape[1],
                                          nuisance_lags, max_lag, batch_frames),
                   f"identification ({n_act} actuators, batches of {batch_frames} frames)")
    beta = _whiten(sequences, nuisance_lags, first, batch_frames)
    power, raw, count, response, norm = _excitation(sequences, beta, nuisance_lags, first, max_lag, batch_frames)
    result.excitation_rms_nm = math.sqrt(power / 2 / count)
    if power <= min_excitation ** 2 * raw:
        message = ("the telemetry holds no excitation: the commands are a function of the past residuals (no "
                   "dither), so the plant cannot be identified from it; record with a white dither")
        warnings.warn(message, PlantNotIdentifiedWarning, stacklevel=2)
        result.warnings.append(message)
        return result

    # WFS lag: where the pooled response of Dwfs(n + l) to the dither innovation u(n) peaks.
    response /= norm
    lag = int(response.abs().argmax())
    if lag > 0:  # wfs recorded `lag` frames late: realign to the documented convention and identify again
        shifted = [_realigned(seq, lag) for seq in sequences]
        again = identify_plant(shifted, grid, radius=radius, nuisance_lags=nuisance_lags, max_lag=max_lag,
                               batch_frames=batch_frames, min_excitation=min_excitation)
        again.lag_frames, again.lag_response = lag, response.tolist()
        again.n_frames, again.warnings = result.n_frames, [
            f"wfs(n) responds to y(n - {lag}), not y(n): the file is {lag} frame(s) behind the documented alignment "
            "and was realigned for identification; realign it (wfs[lag:], y[:-lag]) before training"] + again.warnings
        return again
    result.lag_frames, result.lag_response = lag, response.tolist()
    _response(result, sequences, beta, grid, radius, nuisance_lags, first, batch_frames,
              modal=first_item.modal_basis is not None)
    result.wfs_noise_nm, result.wfs_noise_nm_se = _noise(sequences, result.dm_response("model"), first, batch_frames)
    return result


def identify_working_bytes(n_act: int, n_neighbours: int, nuisance_lags: int, max_lag: int, batch_frames: int) -> int:
    """Bytes identification holds at once, whatever the length of the telemetry: the regressor buffer, a window of
    ``y`` and ``wfs`` (read and transposed), the innovations and increments of a batch."""
    window = (batch_frames + nuisance_lags + 1 + max_lag) * n_act * 8
    return (n_neighbours + 2 * nuisance_lags) * batch_frames * n_act * 8 + 8 * window


def _window(seq, a: int, b: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(K, b - a)`` contiguous ``y`` and ``wfs`` of frames ``a .. b-1`` (a view of memory, or a block read)."""
    return seq.y[a:b].T.contiguous(), seq.wfs[a:b].T.contiguous()


def _realigned(seq, lag: int):
    """``y[:-lag]`` beside ``wfs[lag:]`` (lazy for a streamed file)."""
    if isinstance(seq, StreamedTelemetry):
        return seq.shifted(lag)
    return Telemetry(y=seq.y[:-lag], wfs=seq.wfs[lag:], delay_frames=seq.delay_frames, modal_basis=seq.modal_basis)


def _batches(sequences, p: int, first: int, batch_frames: int, ahead: int = 0):
    """``(seq, a, b, o, y, wfs)`` for frames ``a .. b-1`` of each sequence from ``first`` on, with the window
    ``y, wfs`` ``(K, frames)`` reaching ``p + 1`` frames back and ``ahead`` frames forward; frame ``n`` is column
    ``n - o``."""
    for seq in sequences:
        frames = seq.y.shape[0]
        for a, b in _chunks(first, frames, batch_frames):
            o = a - p - 1
            y, wfs = _window(seq, o, min(b + ahead, frames))
            yield seq, a, b, o, y, wfs


def _whiten(sequences, p: int, first: int, batch_frames: int) -> torch.Tensor:
    """Step 1: the whitening coefficients ``beta`` ``(K, 2p)`` of ``Dy(n)`` on ``z(n)`` (:func:`_innovation`)."""
    whitening = NormalEquations()
    regressors = None
    for _, a, b, o, y, wfs in _batches(sequences, p, first, batch_frames):
        regressors = regressors or _Regressors(y.shape[0], 2 * p, batch_frames)
        whitening.update(regressors.nuisance(y, wfs, p, a - o, b - o).transpose(1, 2),
                         y[:, a - o: b - o] - y[:, a - o - 1: b - o - 1])
    return _solve(whitening)


def _innovation(beta: torch.Tensor, regressors: _Regressors, y: torch.Tensor, wfs: torch.Tensor, p: int, a: int,
                b: int) -> torch.Tensor:
    """``u(n) = Dy(n) - beta . z(n)`` per actuator for window columns ``a .. b-1``, ``(K, b - a)``."""
    fit = torch.bmm(beta.unsqueeze(1), regressors.nuisance(y, wfs, p, a, b)).squeeze(1)
    return y[:, a:b] - y[:, a - 1: b - 1] - fit


def _excitation(sequences, beta: torch.Tensor, p: int, first: int, max_lag: int, batch_frames: int):
    """``(power, raw, count, response, norm)``: the innovations' and the raw command increments' sums of squares
    over ``count`` values, and the pooled response of ``Dwfs(n + l)`` to ``u(n)`` for ``l = 0..max_lag`` with its
    norm ``sum Dy(n) u(n)`` (frames ``first <= n < frames - max_lag``)."""
    power = raw = norm = 0.0
    count = 0
    response = torch.zeros(max_lag + 1, dtype=torch.float64)
    regressors = None
    for seq, a, b, o, y, wfs in _batches(sequences, p, first, batch_frames, ahead=max_lag):
        regressors = regressors or _Regressors(y.shape[0], 2 * p, batch_frames)
        u = _innovation(beta, regressors, y, wfs, p, a - o, b - o)
        increments = y[:, a - o: b - o] - y[:, a - o - 1: b - o - 1]
        power += float(u.pow(2).sum())
        raw += float(increments.pow(2).sum())
        count += u.numel()
        used = min(b, seq.y.shape[0] - max_lag) - a
        if used <= 0:
            continue
        u_used = u[:, :used]
        norm += float((increments[:, :used] * u_used).sum())
        for lag in range(max_lag + 1):
            n0 = a - o + lag
            response[lag] += float(((wfs[:, n0: n0 + used] - wfs[:, n0 - 1: n0 - 1 + used]) * u_used).sum())
    return power, raw, count, response, norm


def _response(result: IdentifiedPlant, sequences, beta: torch.Tensor, grid: ActuatorGrid | ActuatorLayout | None,
              radius: float, p: int, first: int, batch_frames: int, modal: bool = False) -> None:
    """Step 2 and what follows from it: coupling, gains, misregistration, their standard errors (into ``result``)."""
    n_act = beta.shape[0]
    # Without positions each actuator's own dither is its only regressor: the gain needs no geometry.
    neighbours = torch.arange(n_act).unsqueeze(1) if grid is None else grid.neighbours(radius)
    n_nb = neighbours.shape[1]
    regression = NormalEquations()
    regressors = _Regressors(n_act, n_nb + 2 * p, batch_frames)
    whitening = _Regressors(n_act, 2 * p, batch_frames)
    for _, a, b, o, y, wfs in _batches(sequences, p, first, batch_frames):
        u = _innovation(beta, whitening, y, wfs, p, a - o, b - o)
        u_pad = torch.cat([u, torch.zeros_like(u[:1])], 0)  # a zero row for neighbour slots beyond the pupil edge
        features = regressors.nuisance(y, wfs, p, a - o, b - o, offset=n_nb)
        for j in range(n_nb):
            features[:, j].copy_(u_pad[neighbours[:, j]])
        regression.update(features.transpose(1, 2), wfs[:, a - o: b - o] - wfs[:, a - o - 1: b - o - 1])
    weights = _solve(regression)
    gram = regression.gram
    sse = regression.target_power - 2 * (weights * regression.cross).sum(-1) + (
        weights.unsqueeze(1) @ gram @ weights.unsqueeze(-1)).view(-1)
    n_features = (gram.diagonal(dim1=1, dim2=2) > 0).sum(-1)
    residual_var = sse.clamp(min=0) / (regression.n_samples - n_features)
    covariance = residual_var.view(-1, 1, 1) * torch.linalg.pinv(gram, hermitian=True)
    coupling, coupling_cov = weights[:, :n_nb], covariance[:, :n_nb, :n_nb]
    result.residual_rms_nm = float(residual_var.mean().sqrt())
    ones = torch.ones(n_nb, dtype=torch.float64)
    result.identified = True
    result.actuator_gains = coupling.sum(-1).tolist()
    result.actuator_gains_se = (ones @ coupling_cov @ ones).clamp(min=0).sqrt().tolist()
    result.coupling, result.coupling_se = coupling.tolist(), coupling_cov.diagonal(dim1=1, dim2=2).sqrt().tolist()
    result.neighbours = neighbours.tolist()

    offsets, interior, why = coupling_stencils(grid, neighbours, radius, modal)
    if why:
        result.warnings.append(why)
    pooled = interior if interior.any() else torch.ones(n_act, dtype=torch.bool)
    if offsets.ndim == 2:  # a lattice: slot m is the same offset for every actuator, so pool the pattern
        pattern = coupling[pooled].mean(0)
        pattern_cov = coupling_cov[pooled].sum(0) / int(pooled.sum()) ** 2
        gain = float(pattern.sum())
        dx, dy = float(-(offsets[:, 1] @ pattern) / gain), float(-(offsets[:, 0] @ pattern) / gain)

        def se(gradient: torch.Tensor) -> float:
            return float((gradient @ pattern_cov @ gradient).clamp(min=0).sqrt())

        se_x, se_y = se(-(offsets[:, 1] + dx) / gain), se(-(offsets[:, 0] + dy) / gain)
        result.dm_gain, result.dm_gain_se = gain, se(ones)
        result.offsets = offsets.tolist() if offsets.dtype.is_floating_point and (offsets != offsets.round()).any() \
            else offsets.to(torch.int64).tolist()
    else:  # irregular: each actuator's first moments over its own offsets, pooled (delta-method errors)
        c, cov, o = coupling[pooled], coupling_cov[pooled], offsets[pooled]
        n = int(pooled.sum())
        gain = float(c.sum(-1).mean())
        moment = (o * c.unsqueeze(-1)).sum(1).mean(0)  # (row, column) = (y, x)
        dy, dx = float(-moment[0] / gain), float(-moment[1] / gain)

        def se_of(gradient: torch.Tensor) -> float:  # gradient (n, M): d estimate / d coupling of each actuator
            return float(torch.einsum("km,kmj,kj->", gradient, cov, gradient).clamp(min=0).sqrt())

        se_x, se_y = se_of(-(o[..., 1] + dx) / gain / n), se_of(-(o[..., 0] + dy) / gain / n)
        result.dm_gain, result.dm_gain_se = gain, se_of(torch.ones_like(c) / n)
    if interior.any():
        result.misregistration_x, result.misregistration_x_se = dx, se_x
        result.misregistration_y, result.misregistration_y_se = dy, se_y
    if gain < 0:
        result.warnings.append(f"negative DM gain {gain:.3g}: wfs has the opposite sign of the documented convention "
                               "(eps = s + DM(y)); a reconstructor that gives the correction (R @ IM = -I) must be "
                               "negated")
    if result.dm_gain_se > 0.05 * abs(gain):
        result.warnings.append(f"weak excitation: the DM gain {gain:.3g} has a standard error of "
                               f"{result.dm_gain_se:.2g}; record longer or with a larger dither")


def _sources(dm_response, n_act: int, chunk: int = 256, most: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    """``(weight, index)``, ``(K, most)``: the model DM as at most ``most`` sources per actuator (a bilinear shift
    has 4), the largest of its response to each actuator, so that rows of ``(K, frames)`` signals are gathered
    whole. Unit commands go in ``chunk`` actuators at a time: never a ``(K, K)`` matrix (200 MB at 5000)."""
    weight = torch.zeros(n_act, 0, dtype=torch.float64)
    index = torch.zeros(n_act, 0, dtype=torch.int64)
    for a in range(0, n_act, chunk):
        b = min(a + chunk, n_act)
        units = torch.zeros(b - a, n_act, dtype=torch.float64)
        units[torch.arange(b - a), torch.arange(a, b)] = 1.0
        weight = torch.cat([weight, dm_response(units).T], 1)  # column j: what a unit command on a + j applies
        index = torch.cat([index, torch.arange(a, b).expand(n_act, -1)], 1)
        top = weight.abs().topk(min(most, weight.shape[1]), dim=1).indices
        weight, index = weight.gather(1, top), index.gather(1, top)
    return weight, index


def _noise(sequences, dm_response, first: int, batch_frames: int) -> tuple[float, float]:
    """White WFS noise RMS (nm) and its standard error from the structure function of the POL reconstruction."""
    n_act = sequences[0].y.shape[-1]
    weight, index = _sources(dm_response, n_act)
    sums, count = torch.zeros(2, n_act, dtype=torch.float64), 0
    for seq in sequences:
        frames = seq.y.shape[0]
        count += frames - first - 2
        for a, b in _chunks(first, frames - 2, batch_frames):
            y, wfs = _window(seq, a, b + 2)  # s_hat(n + 2) for the last n of the batch
            s_hat = wfs.clone()
            for m in range(index.shape[1]):
                s_hat -= weight[:, m, None] * y[index[:, m]]
            for lag in (1, 2):
                sums[lag - 1] += (s_hat[:, lag: b - a + lag] - s_hat[:, : b - a]).pow(2).sum(-1)
    structure = sums / count
    variance = (4 * structure[0] - structure[1]) / 6  # per actuator, nm^2: D(l) = 2 sigma^2 + c l^2
    mean, se_var = float(variance.mean()), float(variance.std() / math.sqrt(variance.numel()))
    if mean <= 0:
        return 0.0, math.sqrt(se_var)
    sigma = math.sqrt(mean)
    return sigma, se_var / (2 * sigma)
