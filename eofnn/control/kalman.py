"""The per-mode AR(2) turbulence model and its stationary Kalman filter, identified from pseudo-open-loop telemetry
(the model of :func:`eofnn.control.modal.build_lqg`)."""

from __future__ import annotations

import torch

from eofnn.control.classical import DTYPE
from eofnn.control.config import AR_ORDERS, RANDOM_WALK

#: Largest modulus of an identified AR(2) root (an explosive or unit-root fit is pulled inside the unit circle).
MAX_AR_ROOT = 0.99999


def fit_ar2(autocovariance: torch.Tensor, noise_variance: torch.Tensor,
            max_root: float = MAX_AR_ROOT) -> tuple[torch.Tensor, torch.Tensor]:
    """Yule-Walker AR(2) ``(a (K, 2), q (K,))`` from lags 0..2 with the noise variance subtracted at lag 0 (at most
    90% of the smallest eigenvalue of the lag 0..2 Toeplitz covariance, so that it stays positive definite).

    Roots of ``z² - a1 z - a2`` beyond ``max_root`` are pulled to it (same angle); ``q`` is the one-step error
    variance of the resulting model's predictor on the noise-free autocovariance (for a slow mode whose fit was
    pulled in, the stationary-variance ``q`` would be orders of magnitude too small and the filter too sluggish).
    A mode without turbulence (``C(0) <= sigma²``) gets ``a = 0`` and a negligible ``q``: the filter leaves it
    alone.
    """
    c1, c2 = autocovariance[:, 1], autocovariance[:, 2]
    # The noise-free covariance must stay positive definite: subtract at most 90% of the smallest eigenvalue of
    # the measured Toeplitz [[C0, C1, C2], [C1, C0, C1], [C2, C1, C0]] (a smooth mode is nearly deterministic over
    # three frames, so a noise estimate a little too high would leave an explosive fit with negative innovations).
    toeplitz = torch.stack([torch.stack([autocovariance[:, abs(i - j)] for j in range(3)], -1) for i in range(3)], -2)
    subtracted = torch.minimum(noise_variance, 0.9 * torch.linalg.eigvalsh(toeplitz)[:, 0].clamp(min=0))
    c0 = autocovariance[:, 0] - subtracted
    tiny = 1e-12 * autocovariance[:, 0].abs().max().clamp(min=1e-300)
    ok = (c0 > tiny) & (c0.pow(2) - c1.pow(2) > 0)
    det = torch.where(ok, c0.pow(2) - c1.pow(2), torch.ones_like(c0))
    a1 = torch.where(ok, c1 * (c0 - c2) / det, 0.0)
    a2 = torch.where(ok, (c0 * c2 - c1.pow(2)) / det, 0.0)
    roots = torch.stack([(a1 + torch.sqrt((a1.pow(2) + 4 * a2).to(torch.complex128))) / 2,
                         (a1 - torch.sqrt((a1.pow(2) + 4 * a2).to(torch.complex128))) / 2], 1)
    scale = (max_root / roots.abs()).clamp(max=1.0)
    roots = roots * scale
    a1 = (roots[:, 0] + roots[:, 1]).real
    a2 = -(roots[:, 0] * roots[:, 1]).real
    # The one-step error of the model's predictor on the measured covariance, <(x - a1 x(n-1) - a2 x(n-2))²>
    # (the Yule-Walker c0 - a1 c1 - a2 c2 when no root was pulled in).
    q = c0 * (1 + a1.pow(2) + a2.pow(2)) - 2 * a1 * c1 * (1 - a2) - 2 * a2 * c2
    return torch.stack([a1, a2], 1), torch.where(ok, q, tiny).clamp(min=tiny)


def fit_ar1(autocovariance: torch.Tensor, noise_variance: torch.Tensor,
            max_root: float = MAX_AR_ROOT) -> tuple[torch.Tensor, torch.Tensor]:
    """Yule-Walker AR(1) ``x(n + 1) = a1 x(n) + e(n)``, as ``(a (K, 2), q (K,))`` with ``a2 = 0`` (the AR(2) state
    space of :class:`~eofnn.control.classical.ModalLQG` runs it unchanged), from lags 0..1 with the noise variance
    subtracted at lag 0 (at most 90% of the smallest eigenvalue ``C0 - |C1|`` of the lag 0..1 Toeplitz covariance).

    ``|a1|`` is capped at ``max_root``; ``q = c0 (1 + a1²) - 2 a1 c1`` is the one-step error variance of the model's
    predictor on the noise-free autocovariance (``c0 (1 - a1²)`` when nothing was capped). A mode without turbulence
    gets ``a = 0`` and a negligible ``q``, as in :func:`fit_ar2`.
    """
    c1 = autocovariance[:, 1]
    subtracted = torch.minimum(noise_variance, 0.9 * (autocovariance[:, 0] - c1.abs()).clamp(min=0))
    c0 = autocovariance[:, 0] - subtracted
    tiny = 1e-12 * autocovariance[:, 0].abs().max().clamp(min=1e-300)
    ok = c0 > tiny
    a1 = torch.where(ok, c1 / torch.where(ok, c0, torch.ones_like(c0)), 0.0).clamp(-max_root, max_root)
    q = c0 * (1 + a1.pow(2)) - 2 * a1 * c1
    return torch.stack([a1, torch.zeros_like(a1)], 1), torch.where(ok, q, tiny).clamp(min=tiny)


def fit_random_walk(autocovariance: torch.Tensor, noise_variance: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The random walk ``x(n + 1) = x(n) + e(n)`` (``ar_order`` :data:`RANDOM_WALK`), as ``(a (K, 2), q (K,))`` with
    ``a = (1, 0)`` and ``q`` the noise-free one-frame structure function ``D(1) - 2 sigma² = 2 (C0 - sigma² - C1)``.

    Its Kalman filter is exponential smoothing of the POL measurements, ``x_hat <- x_hat + kf (z - x_hat)``, and its
    command the last estimate: at a one-frame delay exactly the integrator of gain ``kf`` (the pseudo-open-loop
    integrator at longer delays), so the integrator's model is inside the LQG's family.
    """
    c0, c1 = autocovariance[:, 0], autocovariance[:, 1]
    tiny = 1e-12 * c0.abs().max().clamp(min=1e-300)
    q = (2 * (c0 - noise_variance.clamp(max=c0 - c1.abs()) - c1)).clamp(min=tiny)
    a = torch.zeros(len(c0), 2, dtype=c0.dtype)
    a[:, 0] = 1.0
    return a, q


def fit_ar(order: int, autocovariance: torch.Tensor, noise_variance: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The turbulence model of :data:`AR_ORDERS` (``(a (K, 2), q (K,))``): :func:`fit_ar1`, :func:`fit_ar2`, or for
    :data:`RANDOM_WALK` (0) :func:`fit_random_walk`."""
    if order not in AR_ORDERS:
        raise ValueError(f"ar_order={order!r} is invalid: it must be one of {', '.join(map(str, AR_ORDERS))} "
                         f"({RANDOM_WALK}: the random walk)")
    fit = {RANDOM_WALK: fit_random_walk, 1: fit_ar1, 2: fit_ar2}[order]
    return fit(autocovariance, noise_variance)


def kalman_gain(ar: torch.Tensor, q: torch.Tensor, r: torch.Tensor,
                iterations: int = 80) -> tuple[torch.Tensor, torch.Tensor]:
    """Stationary Kalman filter gain ``(K, 2)`` and prior (one-step) covariance ``(K, 2, 2)`` per mode.

    ``X(n+1) = A X(n) + [e(n), 0]``, ``z(n) = X_0(n) + v(n)``: the prior covariance solves the discrete algebraic
    Riccati equation ``P = A P A^T - A P C^T (C P C^T + r)^-1 C P A^T + Q``, found for every mode at once by the
    structure-preserving doubling algorithm (quadratic convergence; :func:`scipy.linalg.solve_discrete_are` gives
    the same on well-conditioned modes, see the tests, but fails on the near-unit-root, low-noise ones that slow
    turbulence modes produce). ``r`` is floored at ``1e-9 q`` so that the equation is solvable without noise.
    """
    k = len(q)
    q, r = q.to(DTYPE), torch.maximum(r.to(DTYPE), 1e-9 * q.to(DTYPE)).clamp(min=1e-300)
    a = torch.zeros(k, 2, 2, dtype=DTYPE)
    a[:, 0], a[:, 1, 0] = ar.to(DTYPE), 1.0
    # Control form X = A_c^T X (I + G X)^-1 A_c + H with A_c = A^T, G = C^T C / r, H = Q.
    a_k = a.transpose(1, 2).clone()
    g_k = torch.zeros(k, 2, 2, dtype=DTYPE)
    g_k[:, 0, 0] = 1 / r
    h_k = torch.zeros(k, 2, 2, dtype=DTYPE)
    h_k[:, 0, 0] = q
    eye = torch.eye(2, dtype=DTYPE)
    for _ in range(iterations):
        w = eye + g_k @ h_k
        a_w = a_k @ torch.linalg.inv(w)
        h_next = h_k + a_k.transpose(1, 2) @ h_k @ torch.linalg.solve(w, a_k)
        g_k = g_k + a_w @ g_k @ a_k.transpose(1, 2)
        a_k = a_w @ a_k
        done = bool(((h_next - h_k).abs().amax((1, 2)) <= 1e-13 * h_next.abs().amax((1, 2))).all())
        h_k = h_next
        if done:
            break
    prior = 0.5 * (h_k + h_k.transpose(1, 2))
    gain = prior[:, :, 0] / (prior[:, 0, 0] + r).unsqueeze(1)
    return gain, prior


def prediction_error_variance(ar: torch.Tensor, q: torch.Tensor, prior: torch.Tensor, gain: torch.Tensor,
                              lead: int) -> torch.Tensor:
    """``(K,)`` variance of ``x(n + lead) - x_hat(n + lead | z up to n)`` under the AR(2) model (``lead >= 0``).

    Filtered covariance ``P_f = (I - kf C) P``; ``lead`` steps on: ``A^l P_f A^lT + sum_{j<l} A^j Q A^jT``.
    """
    k = len(q)
    a = torch.zeros(k, 2, 2, dtype=DTYPE)
    a[:, 0], a[:, 1, 0] = ar.to(DTYPE), 1.0
    kc = torch.zeros(k, 2, 2, dtype=DTYPE)
    kc[:, :, 0] = gain
    cov = (torch.eye(2, dtype=DTYPE) - kc) @ prior
    q_mat = torch.zeros(k, 2, 2, dtype=DTYPE)
    q_mat[:, 0, 0] = q
    for _ in range(lead):
        cov = a @ cov @ a.transpose(1, 2) + q_mat
    return cov[:, 0, 0]


# -- models built from a scenario's telemetry -------------------------------------------------------------------
