"""Modal models identified from pseudo-open-loop telemetry: KL modes, per-mode PSD and noise, optimal integrator
gains (Gendron & Lena 1994) and AR(2) Kalman predictors (Kulcsar et al. 2006).

What is estimated, and how (a telescope's telemetry: commands ``y`` and WFS readings ``wfs``, nm):

1. *Recording* (:func:`record_pol_telemetry`): ``data.frames`` frames of a dithered integrator loop
   (``data.integrator_gain``, ``data.dither_nm``) on a stream of its own (``data.seed``, never the test stream); the
   POL reconstruction ``s_hat = wfs - g_model y_applied`` (:func:`eofnn.data.history.pseudo_open_loop`) with the
   model DM gain. The dither checks that model: the WFS response to the dither, ``<wfs(n) w(n)> / ((1 - f) <w²>)``,
   is the DM gain times the WFS gain; a model more than 5% (and 3 standard errors) off is reported as a warning.
2. *Modes*: the Karhunen-Loeve modes of the turbulence on the actuator grid, the eigenvectors of the POL
   covariance (``(K, K)``, orthonormal columns by decreasing variance; white noise adds the same ``sigma²`` to every
   eigenvalue, so the eigenvectors are the turbulence's). Turbulence is statistically homogeneous, so the sample
   covariance is first averaged over all actuator pairs with the same separation on the grid: a few seconds of
   frozen flow span only a few independent pupils, and the eigenvectors of the raw sample covariance are then
   specific to the record (their trailing modes carry far more variance on another stream: ``docs/findings.md``).
3. *Per mode*: the variance ``C(0)``, the structure function ``D(l) = <(x(n) - x(n - l))²>`` at lags 1 and 2 (on
   a common range: differences of slow, large modes are far better estimated this way than as differences of
   autocovariances) giving ``C(l) = C(0) - D(l) / 2``, a Welch PSD of the first difference ``x(n) - x(n-1)``
   (Hann segments of 256 frames, half overlap; differencing whitens the red turbulence so that window leakage
   stays negligible, and the integrator's rejection ``|1 - z^-1|² / |P|²`` applies to it without division), and
   the white-noise variance, the smaller of two upper bounds: the lag-0 deficit of the autocovariance
   extrapolated from lags 1 and 2, ``(4 D(1) - D(2)) / 6`` (white noise adds only at lag 0; the turbulence leaves
   ``(2/3) mean_f P_s (1 - cos w)² >= 0``, small for slow modes), and the median over the top quarter of the
   band of the difference PSD divided by ``|1 - e^{-iw}|²`` (the flat floor of the mode's POL PSD; the better
   bound for fast modes).
4. ``modes: N`` keeps the first ``N`` modes' statistics; the others are pooled (their autocovariances, PSDs and
   noise averaged) so that they share one gain / one AR(2) model, the one that is best for them together.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import warnings
from dataclasses import dataclass

import torch

from eofnn.control.baselines import record_dithered
from eofnn.control.classical import DTYPE, ModalIntegrator, ModalLQG, check_modes, dm_response_polynomial
from eofnn.control.kalman import fit_ar, kalman_gain, prediction_error_variance
from eofnn.data.history import pseudo_open_loop
from eofnn.delay import split_delay
from eofnn.errors import ConfigError, DivergedError
from eofnn.resources import require_memory
from eofnn.seeding import int_seed, torch_generator
from eofnn.sim.scenario import Scenario

#: Frames per Welch segment of the modal PSDs, and the fewest segments a PSD is estimated from.
SEGMENT_FRAMES = 256
MIN_SEGMENTS = 4
#: Smallest DM-gain margin of a modal integrator gain: gains are searched up to ``k_crit / MIN_GAIN_MARGIN``.
MIN_GAIN_MARGIN = 1.05
#: Gain margins the modal integrator's per-mode gains are capped at, tried in closed loop on a stream of their own
#: (the PSD model alone over-promises near the bound; the best-gain integrator's refined scan gets that close).
GAIN_MARGIN_CANDIDATES = (1.02, 1.035, 1.05, 1.08)


def required_frames(n_actuators: int) -> int:
    """Telemetry frames a modal model needs: 2 per actuator (the mode covariance) and 4 PSD segments of 256."""
    return max(MIN_SEGMENTS * SEGMENT_FRAMES, 2 * n_actuators)


def require_telemetry(data, n_actuators: int, modes: int | None, what: str) -> None:
    """One-line :class:`ConfigError` unless ``data`` (a DataConfig) can record the telemetry a modal model needs."""
    check_modes(modes, n_actuators)
    if data.dither_nm <= 0:
        raise ConfigError(f"{what}: data.dither_nm={data.dither_nm!r} is invalid: the model is built from dithered "
                          "closed-loop telemetry (the dither checks the DM model of the POL reconstruction), so it "
                          "must be > 0 (nm)")
    needed = required_frames(n_actuators)
    if data.frames < needed:
        raise ConfigError(f"{what}: data.frames={data.frames} is too few: {n_actuators} actuators need at least "
                          f"{needed} frames of telemetry (2 per actuator for the mode covariance, "
                          f"{MIN_SEGMENTS} PSD segments of {SEGMENT_FRAMES})")


def within_screen(scenario: Scenario, data):
    """``(data, note)``: ``data`` (a DataConfig) whose ``frames`` of telemetry fit one realisation of the scenario's
    exact screen (``atmosphere.screen_frames``), and the line that says how, or ``None`` when they fit as given.

    A telescope records as long as it likes; one realisation of the exact screen holds ``screen_frames`` frames. The
    same number of frames is then recorded as several realisations (independent turbulence, pooled like
    ``data.realisations``) of at most ``screen_frames`` each: the defaults (20000 frames) run on a 10000-frame screen.
    """
    atm = scenario.atmosphere
    if atm.model != "exact" or data.frames <= atm.screen_frames:
        return data, None
    parts = math.ceil(data.frames / atm.screen_frames)
    fitted = dataclasses.replace(data, frames=math.ceil(data.frames / parts), realisations=data.realisations * parts)
    return fitted, (f"data.frames={data.frames} exceeds atmosphere.screen_frames={atm.screen_frames}: the telemetry "
                    f"is recorded as {fitted.realisations} realisation(s) of {fitted.frames} frames (independent "
                    f"turbulence, pooled)")


def _fitted_to_screen(scenario: Scenario, data):
    data, note = within_screen(scenario, data)
    if note is not None:
        warnings.warn(note, stacklevel=3)
    return data


def record_pol_telemetry(scenario: Scenario, data, dm_gain_model: float | None = None) -> tuple[torch.Tensor, dict]:
    """``(pol, info)``: ``(realisations, frames, K)`` POL values (nm) from a dithered integrator loop, and the DM
    gain check (module docstring, step 1). ``dm_gain_model`` ``None`` (a config's unset ``dm_gain_model``) uses
    the DM x WFS gain the dither measures, as a telescope that identified its plant would; a number given is
    kept, and checked against the measurement."""
    n_act = scenario.grid.n_actuators
    require_telemetry(data, n_act, None, "modal telemetry")
    scenario.require_stream_frames(data.frames, f"modal telemetry (data.frames={data.frames})", data.realisations)
    require_memory(8 * 4 * data.realisations * data.frames * n_act,
                   f"modal telemetry of data.frames={data.frames} x {n_act} actuators")
    streams = ("classical-telemetry", "classical-dither", "classical-noise")
    result = record_dithered(scenario, data, data.frames, streams, data.realisations)
    y, wfs = result.telemetry.y, result.telemetry.wfs
    f = scenario.plant.delay_fraction
    # The dither of Dithered, drawn again from its seed: one (realisations, K) draw per frame.
    gen = torch_generator(int_seed(data.seed, streams[1]), "dither")
    dither = torch.stack([torch.randn((y.shape[0], n_act), generator=gen, dtype=y.dtype)
                          for _ in range(y.shape[1])], 1) * data.dither_nm
    power = (1 - f) * dither.pow(2).sum()
    gain = float((wfs * dither).sum() / power)
    gain_se = float((wfs - gain * (1 - f) * dither).std() * dither.pow(2).sum().sqrt() / power)
    source = "given"
    if dm_gain_model is None:
        dm_gain_model, source = gain, "measured from the dither"
    info = {"frames": data.frames, "dither_nm": data.dither_nm, "integrator_gain": data.integrator_gain,
            "dm_gain_model": dm_gain_model, "dm_gain_model_source": source, "dm_gain_from_dither": gain,
            "dm_gain_from_dither_se": gain_se, "warnings": []}
    if abs(gain - dm_gain_model) > max(3 * gain_se, 0.05 * dm_gain_model):
        message = (f"the dither sees a DM x WFS gain of {gain:.3f} +- {gain_se:.3f} but the POL reconstruction "
                   f"assumes dm_gain_model={dm_gain_model:g}: the modal model is built from biased POL values")
        info["warnings"].append(message)
        warnings.warn(message, stacklevel=2)
    return pseudo_open_loop(wfs, y, dm_gain_model, f), info


@dataclass
class ModalStatistics:
    """Per-mode statistics of POL telemetry (module docstring, steps 2-4); variances in nm²."""

    modes: torch.Tensor           # (K, K) orthonormal columns, by decreasing POL variance
    variance: torch.Tensor        # (K,) POL variance of each mode
    autocovariance: torch.Tensor  # (K, 3) lags 0, 1, 2
    psd_difference: torch.Tensor  # (K, F) one-sided Welch PSD of x(n) - x(n-1) per bin (see bin_weights)
    bin_weights: torch.Tensor     # (F,) the weighted sum of a PSD over the bins is the variance
    omega: torch.Tensor           # (F,) bin frequencies, rad/frame
    noise_variance: torch.Tensor  # (K,) white-noise variance
    own_modes: int                # modes with statistics of their own (the others pooled)


def homogeneous_covariance(covariance: torch.Tensor, indices: torch.Tensor) -> torch.Tensor:
    """``(K, K)`` covariance averaged over the actuator pairs that share a separation ``indices[i] - indices[j]``
    (``(K, 2)`` integer grid rows and columns): the estimate of a statistically homogeneous field."""
    indices = torch.as_tensor(indices, dtype=torch.int64)
    span = int(indices.max()) - int(indices.min()) + 1
    diff = indices.unsqueeze(1) - indices.unsqueeze(0) + (span - 1)  # (K, K, 2), non-negative
    bins = (diff[..., 0] * (2 * span - 1) + diff[..., 1]).flatten()
    sums = torch.zeros((2 * span - 1) ** 2, dtype=DTYPE).scatter_add_(0, bins, covariance.flatten())
    counts = torch.zeros_like(sums).scatter_add_(0, bins, torch.ones_like(covariance).flatten())
    return (sums / counts.clamp(min=1))[bins].view_as(covariance)


def modal_statistics(pol: torch.Tensor, own_modes: int | None = None, segment_frames: int = SEGMENT_FRAMES,
                     grid_indices: torch.Tensor | None = None) -> ModalStatistics:
    """Statistics of ``(realisations, frames, K)`` POL values: KL modes, autocovariances, PSDs and noise.

    ``grid_indices`` (``(K, 2)`` rows and columns of the actuators) homogenises the covariance before its
    eigenvectors are taken (module docstring, step 2); without it, the raw sample covariance is used.
    """
    pol = pol.to(DTYPE)
    b, t, k = pol.shape
    check_modes(own_modes, k)
    if t < SEGMENT_FRAMES + 1:
        raise ConfigError(f"telemetry has {t} frames: the modal PSDs need at least {SEGMENT_FRAMES + 1}")
    flat = pol.reshape(-1, k)
    covariance = flat.T @ flat / flat.shape[0]
    if grid_indices is not None:
        covariance = homogeneous_covariance(covariance, grid_indices)
    variance, modes = torch.linalg.eigh(covariance)
    variance, modes = variance.flip(0), modes.flip(1)
    # A reproducible sign: each mode's largest entry positive.
    modes = modes * torch.sign(modes.gather(0, modes.abs().argmax(0, keepdim=True)))
    series = pol @ modes
    c0 = series.pow(2).mean((0, 1))
    structure = [(series[:, 2:] - series[:, 2 - lag: t - lag]).pow(2).mean((0, 1)) for lag in (1, 2)]
    autocov = torch.stack([c0, c0 - structure[0] / 2, c0 - structure[1] / 2], 1)
    window = torch.hann_window(segment_frames, periodic=False, dtype=DTYPE)
    segments = series.diff(dim=1).unfold(1, segment_frames, segment_frames // 2)  # (b, segments, K, L)
    psd = (torch.fft.rfft(segments * window, dim=-1).abs().pow(2) / window.pow(2).sum()).mean((0, 1))
    weights, omega = _bins(psd.shape[-1])
    extrapolated = (4 * structure[0] - structure[1]) / 6
    high = omega > 0.75 * math.pi
    floor = (psd[:, high] / _difference_gain(omega[high])).median(-1).values
    noise = torch.minimum(extrapolated, floor).clamp(min=0)
    own = k if own_modes is None else own_modes
    if own < k:  # the other modes share pooled statistics (one gain / one AR(2) model for them together)
        rest = slice(own, k)
        autocov[rest] = autocov[rest].mean(0)
        psd[rest] = psd[rest].mean(0)
        noise[rest] = noise[rest].mean()
    return ModalStatistics(modes, variance, autocov, psd, weights, omega, noise, own)


def _bins(n_bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights (summing to 1 over a one-sided spectrum of ``n_bins``) and frequencies (rad/frame) of its bins."""
    weights = torch.full((n_bins,), 1.0 / (n_bins - 1), dtype=DTYPE)
    weights[0] = weights[-1] = 0.5 / (n_bins - 1)
    return weights, torch.linspace(0, math.pi, n_bins, dtype=DTYPE)


def _difference_gain(omega: torch.Tensor) -> torch.Tensor:
    """``|1 - e^{-i omega}|²``: what first-differencing does to a PSD."""
    return 2 - 2 * torch.cos(omega)


def _refine(psd: torch.Tensor, factor: int) -> torch.Tensor:
    """``(K, F)`` spectra linearly interpolated onto a grid ``factor`` times finer, ``(K, factor (F - 1) + 1)``."""
    n = psd.shape[-1]
    position = torch.arange(factor * (n - 1) + 1, dtype=DTYPE) / factor
    low = position.floor().long().clamp(max=n - 2)
    frac = position - low
    return psd[:, low] * (1 - frac) + psd[:, low + 1] * frac


# -- optimal modal gains ---------------------------------------------------------------------------------------
def _characteristic(gains: torch.Tensor, delay_frames: float, dm_gain: float) -> torch.Tensor:
    """``(G, L)`` coefficients of ``1 - z^-1 + g k z^-d ((1 - f) + f z^-1)``: an integrator loop at gain ``k``."""
    response = dm_response_polynomial(delay_frames)
    out = dm_gain * gains.to(DTYPE).unsqueeze(1) * response
    out[:, 0], out[:, 1] = out[:, 0] + 1.0, out[:, 1] - 1.0
    return out


def _max_root(p: torch.Tensor) -> torch.Tensor:
    """Largest root modulus of monic ``p`` (rows), from the companion matrix."""
    n = p.shape[-1] - 1
    companion = torch.zeros(p.shape[0], n, n, dtype=DTYPE)
    companion[:, 0] = -p[:, 1:]
    companion[:, 1:, :-1] = torch.eye(n - 1, dtype=DTYPE)
    return torch.linalg.eigvals(companion).abs().amax(-1)


def critical_integrator_gain(delay_frames: float, dm_gain: float = 1.0) -> float:
    """Integrator gain at which the loop (delay ``d + f``, DM gain ``dm_gain``) becomes unstable (bisection)."""
    low, high = 0.0, 8.0 / dm_gain
    for _ in range(60):
        mid = 0.5 * (low + high)
        if float(_max_root(_characteristic(torch.tensor([mid], dtype=DTYPE), delay_frames, dm_gain))[0]) < 1:
            low = mid
        else:
            high = mid
    return low


def integrator_transfer(gains: torch.Tensor, delay_frames: float, dm_gain: float,
                        omega: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(|E|², |N|²)``, ``(G, F)``: rejection ``eps / s`` and noise transfer ``eps / v`` of integrators of
    ``gains`` at ``omega`` (rad/frame): ``E = (1 - z^-1) / P``, ``N = g k z^-d H / P``, ``P`` the characteristic
    polynomial (as :func:`eofnn.analysis.stability.analyse_polynomials` with ``D = 1 - z^-1``, ``N = -k``;
    ``H = (1 - f) + f z^-1``)."""
    response = dm_response_polynomial(delay_frames)
    powers = torch.exp(-1j * omega.unsqueeze(-1) * torch.arange(response.shape[0], dtype=DTYPE))  # (F, L)
    p = _characteristic(gains, delay_frames, dm_gain).to(powers.dtype) @ powers.T
    one_minus = 1 - torch.exp(-1j * omega)
    response = response.to(powers.dtype) @ powers.T
    noise = dm_gain * gains.to(DTYPE).unsqueeze(1) * response
    return (one_minus.abs() ** 2 / p.abs() ** 2), (noise.abs() ** 2 / p.abs() ** 2)


def optimal_gains(stats: ModalStatistics, delay_frames: float, dm_gain_model: float = 1.0, n_grid: int = 400,
                  min_gain_margin: float = MIN_GAIN_MARGIN) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Per mode, the integrator gain minimising the predicted residual variance (nm²).

    ``residual(k) = sum_f w_f (|E_k(f)|² PSD_s(f) + |N_k(f)|² sigma²)`` with ``PSD_s = PSD_pol - sigma²``, over
    ``n_grid`` gains in ``(0, k_crit / min_gain_margin]``: the DM gain may grow by ``min_gain_margin`` before a
    mode goes unstable (without it the slowest modes chose gains near critical, promised by the PSD model but not
    delivered on the test stream: ``docs/findings.md``). Computed as
    ``|E|² PSD_s = PSD_ds / |P|²`` from the difference PSD less its noise ``|1 - e^{-iw}|² sigma²`` (clipped at
    0), interpolated onto a frequency grid 8x finer than the PSD's so that the resonance of a gain near critical
    is resolved. Returns ``(gains, residual, k_crit)``.
    """
    k_crit = critical_integrator_gain(delay_frames, dm_gain_model)
    grid = k_crit / min_gain_margin * torch.arange(1, n_grid + 1, dtype=DTYPE) / n_grid
    fine = _refine(stats.psd_difference, 8)
    weights, omega = _bins(fine.shape[-1])
    rejection, noise_transfer = integrator_transfer(grid, delay_frames, dm_gain_model, omega)
    turbulence = (fine - _difference_gain(omega) * stats.noise_variance.unsqueeze(1)).clamp(min=0)
    residual = (rejection / _difference_gain(omega).clamp(min=1e-300) * weights) @ turbulence.T
    residual = residual + (noise_transfer * weights).sum(-1, keepdim=True) * stats.noise_variance
    best = residual.argmin(0)
    return grid[best], residual[best, torch.arange(residual.shape[1])], k_crit


def _summary(stats: ModalStatistics, info: dict) -> dict:
    """The identified statistics in a few numbers (``metrics.json``)."""
    quantiles = [0.0, 0.5, 1.0]
    return {**info, "n_modes": stats.modes.shape[1], "own_modes": stats.own_modes,
            "mode_variance_nm2": {"first": float(stats.variance[0]), "median": float(stats.variance.median())},
            "noise_rms_nm": {"median": float(stats.noise_variance.median().sqrt()),
                             "quantiles_0_50_100": [float(v) for v in
                                                    stats.noise_variance.sqrt().quantile(torch.tensor(quantiles,
                                                                                                      dtype=DTYPE))]}}


def _quantiles(values: torch.Tensor) -> list[float]:
    return [round(float(v), 6) for v in values.quantile(torch.tensor([0.0, 0.1, 0.5, 0.9, 1.0], dtype=DTYPE))]


def build_modal_integrator(scenario: Scenario, data, modes: int | None = None,
                           dm_gain_model: float | None = None) -> ModalIntegrator:
    """Record telemetry in ``scenario`` and choose one optimal integrator gain per KL mode
    (:func:`optimal_gains`); modes past ``modes`` share the gain best for them together.

    How close to its critical gain a mode may go is chosen like the best-gain integrator's gain: each cap of
    :data:`GAIN_MARGIN_CANDIDATES` closes the loop on a stream of its own (``data.frames`` frames, never the test
    stream) and the lowest median residual wins (``margin_scan`` in the model's info)."""
    data = _fitted_to_screen(scenario, data)
    pol, info, stats = _recorded(scenario, data, dm_gain_model, modes)
    dm_gain_model = info["dm_gain_model"]
    delay = scenario.plant.delay_frames
    settle = min(500, data.frames // 2)
    scan, best = {}, None
    for margin in GAIN_MARGIN_CANDIDATES:
        gains, residual, k_crit = optimal_gains(stats, delay, dm_gain_model, min_gain_margin=margin)
        candidate = ModalIntegrator(stats.modes, gains, delay, dm_gain_model)
        rms = scenario.median_residual_nm(candidate, data.frames, data.seed, "modal-margin", settle,
                                          realisations=data.realisations)
        scan[f"{margin:g}"] = rms
        if rms is not None and (best is None or rms < best[0]):
            best = (rms, margin, gains, residual)
    if best is None:
        raise DivergedError("every per-mode gain cap of the modal integrator diverged in closed loop: the telemetry "
                            "does not describe this plant (check data.dither_nm and the DM gain)")
    _, margin, gains, residual = best
    info = _summary(stats, info)
    info.update({"critical_gain": k_crit, "gain_margin": margin, "margin_scan": scan,
                 "gains_quantiles_0_10_50_90_100": _quantiles(gains),
                 "first_gains": [round(float(g), 4) for g in gains[:10]],
                 "predicted_residual_rms_nm": math.sqrt(float(residual.sum()) / pol.shape[-1])})
    return ModalIntegrator(stats.modes, gains, delay, dm_gain_model, info)


def build_lqg(scenario: Scenario, data, modes: int | None = None, dm_gain_model: float | None = None,
              ar_order: int = 2, noise_scale: float = 1.0) -> ModalLQG:
    """Record telemetry in ``scenario`` and build :func:`lqg_from_pol` from it; modes past ``modes`` share one
    model fitted on their pooled statistics."""
    data = _fitted_to_screen(scenario, data)
    pol, info, stats = _recorded(scenario, data, dm_gain_model, modes)
    return lqg_from_pol(pol, scenario.plant.delay_frames, info["dm_gain_model"], ar_order, modes, info=info,
                        stats=stats, noise_scale=noise_scale)


#: The last two recordings (the LQG of each AR order and the modal integrator of a study share theirs).
_RECORDED: dict[str, tuple] = {}


def _recorded(scenario: Scenario, data, dm_gain_model: float | None, modes: int | None) -> tuple:
    """``(pol, info, stats)`` of :func:`record_pol_telemetry` and :func:`modal_statistics`, once per arguments."""
    key = repr((scenario, data, dm_gain_model, modes))
    if key not in _RECORDED:
        pol, info = record_pol_telemetry(scenario, data, dm_gain_model)
        stats = modal_statistics(pol, modes, grid_indices=torch.as_tensor(scenario.grid.indices))
        while len(_RECORDED) >= 2:
            _RECORDED.pop(next(iter(_RECORDED)))
        _RECORDED[key] = (pol, info, stats)
    pol, info, stats = _RECORDED[key]
    return pol, copy.deepcopy(info), stats


def lqg_from_pol(pol: torch.Tensor, delay_frames: int | float, dm_gain_model: float, ar_order: int = 2,
                 modes: int | None = None, grid_indices: torch.Tensor | None = None, info: dict | None = None,
                 stats: ModalStatistics | None = None, noise_scale: float = 1.0) -> ModalLQG:
    """The LQG of ``(realisations, frames, K)`` POL values (nm) reconstructed with ``dm_gain_model``: KL modes
    (homogenised over ``grid_indices``, the actuators' lattice rows and columns, where given), an AR(``ar_order``)
    per mode (:func:`~eofnn.control.kalman.fit_ar`; 0: the random walk) and its stationary Kalman filter with the
    identified noise variance times ``noise_scale`` (the filter's one knob, scanned in the loop like an integrator's
    gain: :mod:`eofnn.control.lqg_tuning`), for a loop of ``delay_frames`` (:func:`build_lqg` records the POL
    values in a scenario; another simulator's telemetry gives them as well; ``stats``: already computed)."""
    info = dict(info or {})
    stats = modal_statistics(pol, modes, grid_indices=grid_indices) if stats is None else stats
    ar, q = fit_ar(ar_order, stats.autocovariance, stats.noise_variance)
    r = noise_scale * stats.noise_variance
    gain, prior = kalman_gain(ar, q, r)
    d, f = split_delay(delay_frames)
    error = prediction_error_variance(ar, q, prior, gain, d)
    if f:
        error = (1 - f) * error + f * prediction_error_variance(ar, q, prior, gain, d + 1)
    info = _summary(stats, info)
    # (AR(2) and a noise scale of 1, the defaults, are not said: metrics.json keeps the keys of before)
    info.update({key: v for key, v, default in (("ar_order", ar_order, 2), ("noise_scale", noise_scale, 1))
                 if v != default})
    info.update({"ar1_quantiles_0_10_50_90_100": _quantiles(ar[:, 0]),
                 "ar2_quantiles_0_10_50_90_100": _quantiles(ar[:, 1]),
                 "first_ar": [[round(float(v), 6) for v in row] for row in ar[:5]],
                 "innovation_rms_nm_median": float(q.median().sqrt()),
                 "predicted_residual_rms_nm": math.sqrt(float(error.sum()) / pol.shape[-1])})
    return ModalLQG(stats.modes, ar, q, r, gain, delay_frames, dm_gain_model, info)
