"""Classical controllers an AO expert compares a predictor with: POL extrapolation, optimal modal gains, LQG.

All three are linear and time-invariant, so the stability analysis covers them (groups are modes):

- :class:`Extrapolator`: untrained polynomial extrapolation of the pseudo-open-loop (POL) signal over the loop
  delay, run as fixed open-loop EOF weights through :class:`~eofnn.control.predictive.PredictiveController`.
- :class:`ModalIntegrator`: ``y(n) = y(n-1) - M diag(k) M^T wfs(n - d)``, one gain per Karhunen-Loeve mode
  (Gendron & Lena 1994); the modes and gains come from :mod:`eofnn.control.modal`.
- :class:`ModalLQG`: a stationary Kalman filter per mode on the POL modal coefficients with an AR(2) turbulence
  model, and the certainty-equivalent command ``y(n) = -M x_hat(n) / g_model`` (Kulcsar et al. 2006).

Conventions are those of :mod:`eofnn.data.history`: the controller computing ``y(n)`` receives ``wfs(n - d)``
(nm); the POL value of frame ``n - d`` is ``s_hat = wfs(n-d) - g_model ((1 - f) y(n-d) + f y(n-d-1))`` for a
delay ``d + f``; the command ``y(n)`` acts as ``(1 - f) y(n) + f y(n-1)`` over frame ``n``, so the turbulence it
must cancel is ``(1 - f) s(n) + f s(n+1)`` (:func:`eofnn.data.history.blended_target`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import torch

from eofnn.control.config import EXTRAPOLATION_ORDERS, MAX_EXTRAPOLATION_SMOOTHING
from eofnn.control.predictive import PredictiveController
from eofnn.data.history import HistorySpec
from eofnn.delay import split_delay
from eofnn.errors import ConfigError
from eofnn.models.linear import LinearFilter
from eofnn.sim.loop.runner import LoopInput
from eofnn.validation import Interval, OneOf, check_value

DTYPE = torch.float64


# -- polynomial extrapolation -----------------------------------------------------------------------------------
def _lagrange_at(order: int, lead: int) -> torch.Tensor:
    """Weights on ``x(0), x(-1), ..., x(-order)`` of the polynomial through them, evaluated at ``t = lead``."""
    weights = []
    for j in range(order + 1):
        w = 1.0
        for m in range(order + 1):
            if m != j:
                w *= (lead + m) / (m - j)  # node t_m = -m: (t - t_m) / (t_j - t_m)
        weights.append(w)
    return torch.tensor(weights, dtype=DTYPE)


def _least_squares_at(order: int, n_points: int, lead: int) -> torch.Tensor:
    """Weights on ``x(0), ..., x(-(n_points - 1))`` of the least-squares polynomial of degree ``order`` through
    them, evaluated at ``t = lead``: ``v(lead)^T pinv(V)`` with the Vandermonde matrix ``V`` of the nodes."""
    nodes = -torch.arange(n_points, dtype=DTYPE)
    powers = torch.arange(order + 1, dtype=DTYPE)
    vandermonde = nodes.unsqueeze(1) ** powers  # (n_points, order + 1); 0 ** 0 = 1
    return (float(lead) ** powers) @ torch.linalg.pinv(vandermonde)


def _polynomial_at(order: int, smoothing: int, lead: int) -> torch.Tensor:
    """Interpolation through ``order + 1`` values (``smoothing`` 0, the Lagrange weights exactly as before), or the
    least-squares fit over ``order + 1 + smoothing`` values."""
    return _lagrange_at(order, lead) if smoothing == 0 else _least_squares_at(order, order + 1 + smoothing, lead)


def check_extrapolator(order: int, smoothing: int = 0) -> None:
    """``order`` must be one of :data:`EXTRAPOLATION_ORDERS` and ``smoothing`` an integer from 0 to
    :data:`MAX_EXTRAPOLATION_SMOOTHING` (one line otherwise)."""
    check_value("order", order, OneOf(EXTRAPOLATION_ORDERS))
    check_value("smoothing", smoothing, Interval(0, MAX_EXTRAPOLATION_SMOOTHING, integer=True, unit="frames"))


def extrapolation_weights(order: int, delay_frames: int | float, smoothing: int = 0) -> torch.Tensor:
    """``(order + 1 + smoothing,)`` weights ``w`` with ``sum_j w_j s_hat(n - d - j)`` the extrapolated turbulence
    acting at ``n``.

    For a delay ``d + f`` the target is ``(1 - f) s(n) + f s(n + 1)``: the weights extrapolating ``d`` and ``d + 1``
    frames ahead of the newest POL value, blended. Order 1, ``d = 2``: ``[3, -2]``; exact for polynomials of
    degree ``<= order``. ``smoothing`` > 0 fits the polynomial by least squares to that many more POL values: still
    exact for polynomials of degree ``<= order``, but averaging the WFS noise down (order 1 at ``d = 2`` over 4
    values: ``[1.3, 0.6, -0.1, -0.8]``, noise gain 1.64 against 3.61) at the cost of lag on faster turbulence.
    ``order``, ``smoothing`` and the delay are as the extrapolator's config, or :class:`Extrapolator`, and the plant
    checked them (:func:`check_extrapolator`): they are not checked again here.
    """
    d, f = split_delay(delay_frames)
    weights = _polynomial_at(order, smoothing, d)
    return (1 - f) * weights + f * _polynomial_at(order, smoothing, d + 1) if f else weights


def extrapolator_filter(order: int, delay_frames: int | float, dm_gain_model: float = 1.0,
                        smoothing: int = 0) -> tuple[LinearFilter, HistorySpec]:
    """The extrapolator as a shared open-loop :class:`LinearFilter` ``-w / g_model`` and the history it reads."""
    weights = extrapolation_weights(order, delay_frames, smoothing)
    taps = len(weights)
    spec = HistorySpec("open_loop", taps, delay_frames)  # the spec checks the delay (2.0 -> 2)
    network = LinearFilter(1, taps, "shared")
    network.load_solution(-weights.unsqueeze(0) / dm_gain_model)
    return network.eval(), spec


class Extrapolator:
    """Untrained polynomial extrapolation of the POL signal over the loop delay.

    ``y(n) = -(1 / g_model) sum_j w_j s_hat(n - d - j)`` with the weights of :func:`extrapolation_weights` (order 1
    at a two-frame delay: ``y(n) = -(3 s_hat(n-2) - 2 s_hat(n-3))``). Nothing is estimated; the POL reconstruction
    believes the DM gain ``dm_gain_model``. It is built for the plant's delay at :meth:`reset`.

    Parameters
    ----------
    order : {0, 1, 2}
        Degree of the extrapolating polynomial (0: a POL zero-order hold).
    dm_gain_model : float
        DM gain of the POL reconstruction and of the command.
    smoothing : int
        POL values beyond ``order + 1`` the polynomial is fitted to by least squares (0: through ``order + 1``
        values exactly; more averages the WFS noise down at the cost of lag).
    """

    def __init__(self, order: int = 1, dm_gain_model: float = 1.0, smoothing: int = 0) -> None:
        check_extrapolator(order, smoothing)
        self.order, self.dm_gain_model, self.smoothing = order, dm_gain_model, smoothing

    def reset(self, batch: int, n_actuators: int, delay_frames: int | float, dtype: torch.dtype) -> None:
        network, spec = extrapolator_filter(self.order, delay_frames, self.dm_gain_model, self.smoothing)
        self._inner = PredictiveController(network, spec, self.dm_gain_model)
        self._inner.reset(batch, n_actuators, delay_frames, dtype)

    def step(self, inp: LoopInput) -> torch.Tensor:
        return self._inner.step(inp)


# -- polynomials in z^-1 (the analysis floor has its own; control may not import it) --------------------------------
def _multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise product of ``(..., La)`` and ``(..., Lb)`` coefficient tensors in ``z^-1``."""
    shape = torch.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    out = torch.zeros(*shape, a.shape[-1] + b.shape[-1] - 1, dtype=DTYPE)
    for j in range(b.shape[-1]):
        out[..., j: j + a.shape[-1]] += a * b[..., j: j + 1]
    return out


def _add(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    n = max(a.shape[-1], b.shape[-1])
    pad = torch.nn.functional.pad
    return pad(a, (0, n - a.shape[-1])) + pad(b, (0, n - b.shape[-1]))


def dm_response_polynomial(delay_frames: int | float) -> torch.Tensor:
    """``z^-d ((1 - f) + f z^-1)``: the DM's response to a command after ``d + f`` frames."""
    d, f = split_delay(delay_frames)
    out = torch.zeros(d + 2, dtype=DTYPE)
    out[d], out[d + 1] = 1 - f, f
    return out


# -- modal controllers ------------------------------------------------------------------------------------------
@dataclass
class ModalIntegrator:
    """Integrator with one gain per mode: ``y(n) = y(n-1) - M diag(k) M^T wfs(n - d)`` (Gendron & Lena 1994).

    Attributes
    ----------
    modes : Tensor
        ``(K, K)`` orthonormal modes on the actuator grid, one per column (KL modes of the POL telemetry, by
        decreasing variance).
    gains : Tensor
        ``(K,)`` integrator gain of each mode (dimensionless).
    delay_frames : float
        The delay the gains were chosen for.
    dm_gain_model : float
        DM gain the gains were chosen for (the controller itself has no POL reconstruction).
    info : dict
        What was estimated (for ``metrics.json``).
    """

    modes: torch.Tensor
    gains: torch.Tensor
    delay_frames: int | float
    dm_gain_model: float = 1.0
    info: dict | None = None

    def reset(self, batch: int, n_actuators: int, delay_frames: int | float, dtype: torch.dtype) -> None:
        _check_shape(self.modes, n_actuators, delay_frames, self.delay_frames)
        self._m = self.modes.to(dtype)
        self._k = self.gains.to(dtype)
        self._y = torch.zeros(batch, n_actuators, dtype=dtype)

    def step(self, inp: LoopInput) -> torch.Tensor:
        self._y = self._y - ((inp.wfs @ self._m) * self._k) @ self._m.T
        return self._y

    def polynomials(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Per mode ``(D, N)`` with ``D(z) y = N(z) u``: ``D = 1 - z^-1``, ``N = -k`` (``u = wfs(n - d)``)."""
        k = self.gains.to(DTYPE)
        return torch.tensor([1.0, -1.0], dtype=DTYPE).expand(len(k), 2).clone(), -k.unsqueeze(1)


@dataclass
class ModalLQG:
    """Stationary Kalman filter and certainty-equivalent LQG command per mode, AR(2) turbulence model.

    Per mode ``x(n + 1) = a1 x(n) + a2 x(n - 1) + e(n)`` (innovation variance ``q``, nm²), measured through the POL
    reconstruction ``z(n) = m^T s_hat(n) = x(n) + v(n)`` (noise variance ``r``, nm²). With the state
    ``X = [x(n), x(n-1)]``, ``A = [[a1, a2], [1, 0]]`` and the stationary Kalman gain ``kf`` (filter form), at frame
    ``n`` the controller updates ``X(n-d|n-d) = F X(n-d-1|n-d-1) + kf z(n-d)`` with ``F = (I - kf C) A`` and
    commands ``y(n) = -M (L X(n-d|n-d)) / g_model``, ``L = C A^d ((1 - f) I + f A)``: the predicted turbulence
    averaged over the frames ``y(n)`` acts on (the DM term is known, so the LQG command reduces to cancelling the
    predicted turbulence).

    Attributes
    ----------
    modes : Tensor
        ``(K, K)`` orthonormal modes (columns).
    ar : Tensor
        ``(K, 2)`` AR(2) coefficients ``a1, a2`` per mode.
    innovation_variance, noise_variance : Tensor
        ``(K,)`` ``q`` and ``r`` per mode, nm².
    kalman_gain : Tensor
        ``(K, 2)`` stationary filter gain ``kf``.
    delay_frames : float
        Loop delay ``d + f`` the predictor is built for.
    dm_gain_model : float
        DM gain of the POL reconstruction and of the command.
    info : dict
        What was estimated (for ``metrics.json``).
    """

    modes: torch.Tensor
    ar: torch.Tensor
    innovation_variance: torch.Tensor
    noise_variance: torch.Tensor
    kalman_gain: torch.Tensor
    delay_frames: int | float
    dm_gain_model: float = 1.0
    info: dict | None = None

    @property
    def transition(self) -> torch.Tensor:
        """``(K, 2, 2)`` state transition ``A``."""
        a = self.ar.to(DTYPE)
        out = torch.zeros(len(a), 2, 2, dtype=DTYPE)
        out[:, 0], out[:, 1, 0] = a, 1.0
        return out

    @property
    def filter_matrix(self) -> torch.Tensor:
        """``F = (I - kf C) A``, ``(K, 2, 2)``."""
        a = self.transition
        kc = torch.zeros_like(a)
        kc[:, :, 0] = self.kalman_gain.to(DTYPE)
        return (torch.eye(2, dtype=DTYPE) - kc) @ a

    @property
    def output_row(self) -> torch.Tensor:
        """``L = C A^d ((1 - f) I + f A)``, ``(K, 2)``: the predicted turbulence acting during frame ``n``."""
        d, f = split_delay(self.delay_frames)
        a = self.transition
        blend = (1 - f) * torch.eye(2, dtype=DTYPE) + f * a
        return (torch.linalg.matrix_power(a, d) @ blend)[:, 0]

    def reset(self, batch: int, n_actuators: int, delay_frames: int | float, dtype: torch.dtype) -> None:
        _check_shape(self.modes, n_actuators, delay_frames, self.delay_frames)
        self._d, self._f = split_delay(delay_frames)
        self._m = self.modes.to(dtype)
        f_mat = self.filter_matrix.to(dtype)
        self._filter = ((f_mat[:, 0, 0], f_mat[:, 0, 1]), (f_mat[:, 1, 0], f_mat[:, 1, 1]))
        self._gain = self.kalman_gain.to(dtype).T
        self._out = (-self.output_row / self.dm_gain_model).to(dtype).T
        zeros = torch.zeros(batch, self.modes.shape[1], dtype=dtype)
        self._state = (zeros, zeros)  # x(n-d|n-d) and x(n-d-1|n-d) per mode, (batch, K) each
        zeros = torch.zeros(batch, n_actuators, dtype=dtype)
        self._past = deque([zeros] * (self._d + 1), maxlen=self._d + 1)  # y(n-1), ..., y(n-d-1)

    def step(self, inp: LoopInput) -> torch.Tensor:
        d, f = self._d, self._f
        applied = self._past[d - 1] if not f else (1 - f) * self._past[d - 1] + f * self._past[d]
        z = (inp.wfs - self.dm_gain_model * applied) @ self._m  # POL modal coefficients of frame n - d
        # X <- F X + kf z per mode, written out for the 2x2 blocks (an einsum costs more than the arithmetic).
        x0, x1 = self._state
        (f00, f01), (f10, f11) = self._filter
        self._state = (f00 * x0 + f01 * x1 + self._gain[0] * z, f10 * x0 + f11 * x1 + self._gain[1] * z)
        y = (self._out[0] * self._state[0] + self._out[1] * self._state[1]) @ self._m.T
        self._past.appendleft(y)
        return y

    def polynomials(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Per mode ``(D, N)`` with ``D(z) y = N(z) u`` on the reading ``u(n) = wfs(n - d)``.

        From the POL value ``z_d = u - g_model z^-d H y`` to the command, the filter is ``W = N_w / D_w`` with
        ``D_w = det(I - z^-1 F) = 1 - tr(F) z^-1 + det(F) z^-2`` and ``N_w = -L adj(I - z^-1 F) kf / g_model``,
        ``adj(I - z^-1 F) = I - z^-1 adj(F)``; the POL coupling then gives ``D = D_w + g_model z^-d H N_w``,
        ``N = N_w`` (as for open-loop EOF, :func:`eofnn.analysis.stability.controller_polynomials`).
        """
        f_mat, k, row = self.filter_matrix, self.kalman_gain.to(DTYPE), self.output_row
        trace = f_mat[:, 0, 0] + f_mat[:, 1, 1]
        det = f_mat[:, 0, 0] * f_mat[:, 1, 1] - f_mat[:, 0, 1] * f_mat[:, 1, 0]
        d_w = torch.stack([torch.ones_like(trace), -trace, det], 1)
        adj = torch.stack([torch.stack([f_mat[:, 1, 1], -f_mat[:, 0, 1]], -1),
                           torch.stack([-f_mat[:, 1, 0], f_mat[:, 0, 0]], -1)], -2)
        n0 = (row * k).sum(-1)
        n1 = -(row * (adj @ k.unsqueeze(-1)).squeeze(-1)).sum(-1)
        n_w = -torch.stack([n0, n1], 1) / self.dm_gain_model
        d_poly = _add(d_w, self.dm_gain_model * _multiply(dm_response_polynomial(self.delay_frames), n_w))
        return d_poly, n_w


def _check_shape(modes: torch.Tensor, n_actuators: int, delay_frames: float, built_for: float) -> None:
    if modes.shape[0] != n_actuators:
        raise ConfigError(f"the modal controller was built for {modes.shape[0]} actuators but the loop has "
                          f"{n_actuators}")
    if float(delay_frames) != float(built_for):
        raise ConfigError(f"the modal controller was built for delay_frames={built_for} but the plant has "
                          f"delay_frames={delay_frames}")


def check_modes(modes: int | None, n_actuators: int) -> None:
    """``modes`` (the modes with a parameter of their own) must be between 1 and the number of actuators."""
    if modes is not None:
        check_value("modes", modes, Interval(1, n_actuators, integer=True, unit=f"the grid has {n_actuators} "
                                                                                "actuators"))
