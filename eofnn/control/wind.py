"""Frozen-flow layers (winds and weights) identified from pseudo-open-loop telemetry.

A layer moving at ``v`` carries the map of frame ``n`` to frame ``n + tau`` shifted by ``v tau T``. The
cross-spectrum of a late frame with an early one, ``X_k(tau) = sum_n b_k(n + tau) a_k(n)*`` (``a``, ``b``: Fourier
modes of the two maps), is then ``sum_l w_l X_k(0) exp(-2 pi i k.v_l tau T)``: the lag-0 cross-spectrum turned by
each layer's displacement, ``w_l`` the layer's share of the turbulence (layers of the same outer scale have the same
spectrum). ``a`` is the map of the early frame extended over the FFT grid (:class:`~eofnn.control.fourier.
FourierBasis`), ``b`` the late frame at the pupil's actuators only, zero elsewhere: their cross-correlation is a
sum over the actuators of the late frame, so the model is that of a cross-correlation peak moving with the wind,
whatever the pupil. Both maps are first whitened by the discrete Laplacian (the early one on the periodic grid, the
late one at the actuators whose four neighbours are active): it sharpens the peak, and it removes piston, tip and
tilt, which a simulation takes out of every frame and which break the shift. Modes up to 0.3 cycles per pitch
are fitted (whitening raises the aliases, which a higher limit lets in: ``docs/findings.md``).

The fit: at four lags (the longest the time the fastest wind takes to move 4 pitches or a quarter of the pupil, so
that two layers' peaks part by more than their width), layers are found one at a time, each the best single layer
over a grid of winds (``|v| <= max_speed``, a quarter of a pitch of displacement per step at the longest lag, a
quarter of the peak's width) against what the layers found so far leave unexplained, then every wind and weight is
refined together by least squares. A layer under 10% of the weight is dropped; weights are normalised.
``tests/test_pfc.py`` checks one layer's speed within 2% and direction within 2 degrees, and two layers' speeds within 10%
with their weights within 0.1 (what was measured: ``docs/findings.md``).

What did not work: the phases of each Fourier mode's own lag covariance (``k.v T`` per frame, Poyneer et al.'s
approach) come out slow (``docs/findings.md``): the pupil mixes each mode with its neighbours, and the phase is that
of a frequency below ``k``. Lagged covariances or structure functions of the maps over pairs of
actuators: dominated by the large scales of a few pupils' worth of screen, and broken by the removal of piston,
tip and tilt from every frame.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from eofnn.control.fourier import DTYPE, FourierBasis
from eofnn.errors import ConfigError

#: A layer identified with less than this share of the weight is dropped.
MIN_LAYER_WEIGHT = 0.1


#: The displacement of the fastest wind at the longest lag: this many pitches, or a quarter of the pupil if more.
LONGEST_SHIFT_PITCHES = 4.0
#: The highest frequency fitted, cycles per pitch.
HIGHEST_CYCLES_PER_PITCH = 0.3


def wind_lags(n_across: int, pitch_m: float, max_speed_mps: float, frame_period_s: float, frames: int,
              shift_pitches: float | None = None) -> list[int]:
    """Four lags (frames), the longest the time ``max_speed_mps`` takes to move :data:`LONGEST_SHIFT_PITCHES` or a
    quarter of the pupil, whichever is more (two layers' peaks must part by more than their width, about a pitch);
    ``shift_pitches`` replaces that displacement."""
    shift = (max(LONGEST_SHIFT_PITCHES, n_across / 4) if shift_pitches is None else shift_pitches) * pitch_m
    longest = max(1, min(int(shift / (max_speed_mps * frame_period_s)), frames // 4))
    return sorted({max(1, round(longest / 2**j)) for j in range(4)})


def _laplacian(maps: torch.Tensor) -> torch.Tensor:
    """The periodic 5-point Laplacian of ``(..., N, N)`` maps."""
    return 4 * maps - sum(maps.roll(step, dim) for step in (1, -1) for dim in (-1, -2))


def cross_spectra(pol: torch.Tensor, basis: FourierBasis, lags: list[int], keep: torch.Tensor,
                  chunk: int = 256) -> torch.Tensor:
    """``(1 + len(lags), M_keep)`` cross-spectra ``X_k(tau)`` (module docstring) of ``(R, T, K)`` POL maps at lag 0
    and ``lags``, modes ``keep``, each the mean over the frame pairs."""
    grid, size = basis.grid, basis.size
    k = grid.n_actuators
    neighbours = grid.neighbours(1.0)  # (K, 5): itself first; k beyond the edge
    interior = (neighbours < k).all(1).to(DTYPE)
    every = [0, *lags]
    b, t, _ = pol.shape
    total = torch.zeros(len(every), int(keep.sum()), dtype=torch.complex128)
    for start in range(0, t, chunk):
        stop = min(start + chunk, t)
        values = pol[:, start: min(stop + max(every), t)].to(DTYPE)
        early = torch.fft.rfft2(_laplacian(basis.extend(values))).flatten(-2)[..., keep]
        padded = torch.nn.functional.pad(values, (0, 1))
        whitened = (4 * values - padded[..., neighbours[:, 1:]].sum(-1)) * interior
        maps = torch.zeros(*values.shape[:-1], size * size, dtype=DTYPE)
        maps[..., basis._pixels] = whitened
        late = torch.fft.rfft2(maps.view(*values.shape[:-1], size, size)).flatten(-2)[..., keep]
        for i, tau in enumerate(every):
            last = min(stop, t - tau) - start
            if last > 0:
                total[i] += (late[:, tau: tau + last] * early[:, :last].conj()).sum((0, 1))
    return total / torch.tensor([b * (t - tau) for tau in every], dtype=DTYPE).unsqueeze(1)


def identify_winds(pol: torch.Tensor, basis: FourierBasis, frame_period_s: float, n_layers: int,
                   max_speed_mps: float, shift_pitches: float | None = None) -> list[dict]:
    """Layers ``[{"vx_mps", "vy_mps", "speed_mps", "direction_deg", "weight"}]`` (weights sum to 1, strongest
    first) of ``(R, T, K)`` POL values on ``basis``'s grid (module docstring); ``shift_pitches``: the fastest wind's
    displacement at the longest lag (:func:`wind_lags`; longer lags part layers of close winds)."""
    from scipy.optimize import least_squares

    pitch = basis.grid.pitch_m
    keep = (basis.frequencies.norm(dim=1) <= HIGHEST_CYCLES_PER_PITCH / pitch) & (basis.frequencies.norm(dim=1) > 0)
    if int(keep.sum()) < 8:
        raise ConfigError(f"the grid has {int(keep.sum())} Fourier modes to identify winds from: too few (give "
                          "pfc.winds, or a grid of more actuators)")
    lags = wind_lags(basis.grid.n_across, pitch, max_speed_mps, frame_period_s, pol.shape[1], shift_pitches)
    spectra = cross_spectra(pol, basis, lags, keep).numpy()
    x0, data = spectra[0], spectra[1:]
    f = basis.frequencies[keep].numpy()
    lag_s = np.asarray(lags, dtype=float) * frame_period_s
    scale = float(np.abs(x0).max()) or 1.0

    def model(params: np.ndarray) -> np.ndarray:  # (lags, M)
        n = len(params) // 3
        phase = f @ params[: 2 * n].reshape(n, 2).T  # (M, layers): k.v
        return np.einsum("l,tml->tm", params[2 * n:], x0[None, :, None] * np.exp(-2j * np.pi * lag_s[:, None, None]
                                                                                  * phase[None]))

    def refine(params: np.ndarray) -> np.ndarray:
        n = len(params) // 3
        low = np.concatenate([np.full(2 * n, -1.5 * max_speed_mps), np.zeros(n)])
        high = np.concatenate([np.full(2 * n, 1.5 * max_speed_mps), np.full(n, 2.0)])

        def residual(p: np.ndarray) -> np.ndarray:
            diff = ((model(p) - data) / scale).ravel()
            return np.concatenate([diff.real, diff.imag])
        return least_squares(residual, np.clip(params, low + 1e-9, high - 1e-9), bounds=(low, high),
                             x_scale="jac").x

    step = max(pitch / (4 * lag_s[-1]), max_speed_mps / 100)
    axis = np.arange(-max_speed_mps, max_speed_mps + step / 2, step)
    candidates = np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    candidates = candidates[np.hypot(*candidates.T) <= max_speed_mps + 1e-9]
    params = np.zeros(0)
    for _ in range(n_layers):
        left = data[-1] - (model(params)[-1] if len(params) else 0.0)
        score = np.concatenate([(np.exp(2j * np.pi * lag_s[-1] * (candidates[i: i + 512] @ f.T)) @ (x0.conj() * left))
                                .real for i in range(0, len(candidates), 512)])
        best = int(np.argmax(score))
        n = len(params) // 3
        weight = max(score[best] / float(np.sum(np.abs(x0) ** 2)), 0.05)
        params = refine(np.concatenate([params[: 2 * n], candidates[best], params[2 * n:], [weight]]))
    n = len(params) // 3
    keep_layer = params[2 * n:] >= MIN_LAYER_WEIGHT * params[2 * n:].sum()
    if keep_layer.sum() < n:
        params = refine(np.concatenate([params[: 2 * n].reshape(n, 2)[keep_layer].ravel(), params[2 * n:][keep_layer]]))
        n = len(params) // 3
    winds, weights = params[: 2 * n].reshape(n, 2), params[2 * n:]
    return [{"vx_mps": float(winds[i, 0]), "vy_mps": float(winds[i, 1]), "speed_mps": float(np.hypot(*winds[i])),
             "direction_deg": float(math.degrees(math.atan2(winds[i, 1], winds[i, 0]))),
             "weight": float(weights[i] / weights.sum())} for i in np.argsort(-weights)]


def known_winds(winds: list[list[float]]) -> list[dict]:
    """``pfc.winds`` (``[speed_mps, direction_deg, weight]`` each) as :func:`identify_winds` gives layers."""
    total = sum(w[2] for w in winds)
    return [{"vx_mps": s * math.cos(math.radians(a)), "vy_mps": s * math.sin(math.radians(a)), "speed_mps": float(s),
             "direction_deg": float(a), "weight": w / total} for s, a, w in winds]
