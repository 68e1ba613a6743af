"""Frozen-flow layers identified from pseudo-open-loop telemetry, and the predictive Fourier controller built on
them (:class:`~eofnn.control.fourier.FourierPredictor`).

What is estimated, and how (a telescope's telemetry: commands and WFS readings, nm):

1. *Recording*: the dithered-integrator telemetry and POL reconstruction of the modal controllers
   (:func:`eofnn.control.modal.record_pol_telemetry`, the DM gain measured from the dither).
2. *Noise*: the white-noise variance per actuator, the lag-0 deficit of each actuator's POL autocovariance
   extrapolated from lags 1 and 2, ``(4 D(1) - D(2)) / 6`` (``D`` the temporal structure function; white noise adds
   at lag 0 only), averaged over the actuators.
3. *Winds* (:func:`eofnn.control.wind.identify_winds`): the lagged cross-spectra of the (whitened) POL maps, each
   the lag-0 one turned by the layers' displacements, fitted by least squares (``pfc.winds`` given instead: taken
   as they are).
4. *Per mode*: the variance of each Fourier mode less its noise, smoothed over rings of equal frequency
   (:func:`smooth_variance`), split over layers and aliases
   (:mod:`eofnn.control.fourier`, choice 2); piston, tip and tilt are left out of the command when the telemetry
   holds no more of them than its noise.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from eofnn.control.config import PfcConfig
from eofnn.control.fourier import DTYPE, FourierBasis, FourierPredictor, state_frequencies, stationary_gain
from eofnn.control.modal import record_pol_telemetry, within_screen
from eofnn.control.wind import identify_winds, known_winds
from eofnn.errors import ConfigError
from eofnn.sim.atmosphere.exact import von_karman_psd
from eofnn.sim.scenario import Scenario
from eofnn.sim.sensing.kernels import kernel_power


def white_noise_variance(pol: torch.Tensor) -> float:
    """White-noise variance per actuator (nm²) of ``(realisations, frames, K)`` POL values (module docstring, 2)."""
    pol = pol.to(DTYPE)
    d1 = (pol[:, 2:] - pol[:, 1:-1]).pow(2).mean((0, 1))
    d2 = (pol[:, 2:] - pol[:, :-2]).pow(2).mean((0, 1))
    return float(((4 * d1 - d2) / 6).clamp(min=0).mean())


def alias_power(frequencies: torch.Tensor, aliases: int, pitch_m: float, outer_scale_m: float,
                kernel: str) -> torch.Tensor:
    """``(M, A)`` power of each mode's aliases ``k + m / pitch`` (arbitrary units): the von Karman spectrum (outer
    scale ``outer_scale_m``) seen through the sensing ``kernel``."""
    f = state_frequencies(frequencies, aliases, pitch_m).numpy()
    power = von_karman_psd(np.hypot(f[..., 0], f[..., 1]), 1.0, outer_scale_m)
    seen = kernel_power(kernel, pitch_m, f[..., 0], f[..., 1], np.float64(1.0), np.float64(0.0))
    return torch.as_tensor(power if seen is None else power * seen)


def smooth_variance(variance: torch.Tensor, model: torch.Tensor, frequencies: torch.Tensor,
                    spacing: float) -> torch.Tensor:
    """``(M,)`` mode variances smoothed over rings: ``model`` (the expected shape) times the ring average of
    ``variance / model``, rings ``spacing`` (cycles/m, the FFT's) wide. Turbulence is isotropic, and a few seconds of
    frozen flow span only a few independent pupils: each mode's own sample variance scatters, and the mode whose
    variance is highest by chance has the largest Kalman gain and sets the analytic DM-gain limit (smoothing brings
    it nearer the simulated one: ``docs/findings.md``)."""
    ring = torch.round(frequencies.norm(dim=1) / spacing).long()
    ratio = variance / model
    total = torch.zeros(int(ring.max()) + 1, dtype=DTYPE).index_add_(0, ring, ratio)
    count = torch.zeros_like(total).index_add_(0, ring, torch.ones_like(ratio))
    return model * (total / count)[ring]


def pfc_from_pol(pol: torch.Tensor, scenario: Scenario, config: PfcConfig | None = None,
                 dm_gain_model: float = 1.0, info: dict | None = None,
                 noise_variance: float | None = None, noise_shape: torch.Tensor | None = None) -> FourierPredictor:
    """The predictive Fourier controller of ``(realisations, frames, K)`` POL values recorded in ``scenario``: noise
    (``noise_variance``, nm² per actuator, where known; else estimated), winds (``config.winds`` if given, else
    identified), per-mode variances and Kalman gains (module docstring). ``noise_shape`` ``(K, K)`` (e.g. ``R W
    R^T``, a Shack-Hartmann's slope noise through its reconstructor): the noise's covariance up to a factor, scaled
    so that its mean diagonal is that variance per actuator; each mode's noise is then ``(F^H C F)_kk`` rather than
    white noise's (``None``: white)."""
    config = config or PfcConfig()
    grid, period = scenario.grid, 1.0 / scenario.frame_rate_hz
    pol = pol.to(DTYPE)
    basis = FourierBasis(grid, config.padding)
    b, t, k = pol.shape
    sigma2 = white_noise_variance(pol) if noise_variance is None else noise_variance
    if noise_shape is None:
        noise = sigma2 * basis.noise_gain()
    else:
        shape = torch.as_tensor(noise_shape, dtype=DTYPE)
        if shape.shape != (k, k):
            raise ConfigError(f"noise_shape of shape {tuple(shape.shape)} does not fit: expected ({k}, {k}) "
                              f"({k} actuators)")
        forward = basis.forward(torch.eye(k, dtype=DTYPE))  # (K, M): mode k of actuator j's unit value
        coloured = (forward.conj() * basis.forward(shape)).sum(0).real  # diag(F^H C F), C symmetric
        noise = sigma2 * coloured.clamp(min=0) / float(shape.diagonal().mean())
    flat = pol.reshape(b * t, k)
    measured = sum(basis.forward(flat[i: i + 512]).abs().pow(2).sum(0) for i in range(0, b * t, 512)) / (b * t)
    variance = (measured - noise).clamp(min=1e-12 * float(noise.max() + 1))
    ptt = pol @ torch.as_tensor(grid.ptt_basis(), dtype=DTYPE)
    remove_ptt = bool((ptt.pow(2).mean((0, 1)) <= 4 * sigma2 + 1e-9 * float(pol.pow(2).mean())).all())
    if config.winds is not None:
        layers = known_winds(config.winds)
    else:
        layers = identify_winds(pol, basis, period, config.layers, config.max_speed_mps)
    velocity = torch.tensor([[lay["vx_mps"], lay["vy_mps"]] for lay in layers], dtype=DTYPE)  # (L, 2)
    weight = torch.tensor([lay["weight"] for lay in layers], dtype=DTYPE)
    true_f = state_frequencies(basis.frequencies, config.aliases, grid.pitch_m)  # (M, A, 2)
    power = alias_power(basis.frequencies, config.aliases, grid.pitch_m, scenario.atmosphere.outer_scale_m,
                        scenario.atmosphere.sensing_kernel)
    share = power / power.sum(1, keepdim=True)
    variance = smooth_variance(variance, power.sum(1), basis.frequencies, 1 / (basis.size * grid.pitch_m))
    phase = torch.einsum("mai,li->mla", true_f, velocity) * period  # (M, L, A) cycles per frame
    transition = (config.alpha * torch.exp(-2j * math.pi * phase)).flatten(1)  # (M, S)
    q = ((1 - config.alpha**2) * variance.view(-1, 1, 1) * weight.view(1, -1, 1) * share.unsqueeze(1)).flatten(1)
    gain, _ = stationary_gain(transition, q, noise)
    info = dict(info or {})
    info.update({"layers": [{key: round(value, 4) for key, value in lay.items()} for lay in layers],
                 "winds_source": "given (pfc.winds)" if config.winds is not None else "identified from telemetry",
                 "noise_rms_nm": math.sqrt(sigma2), "remove_ptt": remove_ptt, "fft_size": basis.size,
                 "n_modes": basis.n_modes, "states_per_mode": transition.shape[1], "alpha": config.alpha})
    if noise_shape is not None:
        info["noise_covariance"] = "coloured (noise_shape)"
    return FourierPredictor(basis, transition, gain, scenario.plant.delay_frames, dm_gain_model, remove_ptt, info)


def build_pfc(scenario: Scenario, data, config: PfcConfig | None = None,
              dm_gain_model: float | None = None) -> FourierPredictor:
    """Record ``data`` (a DataConfig) telemetry in ``scenario`` and build the predictive Fourier controller from it
    (:func:`pfc_from_pol`) with the DM gain the dither measures (or ``dm_gain_model`` if given)."""
    data, note = within_screen(scenario, data)
    if note is not None:
        warnings.warn(note, stacklevel=2)
    pol, info = record_pol_telemetry(scenario, data, dm_gain_model)
    shape = reconstructed_noise_shape(scenario) if config is not None and config.noise_covariance == "reconstructor" \
        else None
    return pfc_from_pol(pol, scenario, config, info["dm_gain_model"], info, noise_shape=shape)


def reconstructed_noise_shape(scenario: Scenario) -> torch.Tensor | None:
    """``R W R^T`` ``(K, K)``: the shape of a Shack-Hartmann scenario's measurement noise on the actuators, its white
    slope noise (``W``: each slope's relative variance) through the reconstructor the loop applies (least squares or
    MMSE); ``None`` for the zonal sensor, whose noise is white."""
    if not scenario.sensor.is_shack_hartmann:
        return None
    turbulence = scenario.turbulence(0, "noise-shape")
    ops = turbulence.operators
    mmse = turbulence.reconstructor(scenario.plant.wfs_noise_nm)
    r = ops.reconstructor if mmse is None else mmse
    weights = torch.as_tensor(ops.sensor.slope_noise_scale, dtype=DTYPE) ** 2
    return (r * weights) @ r.T
