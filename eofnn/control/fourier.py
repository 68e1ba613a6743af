"""Predictive Fourier control (Poyneer, Macintosh & Veran 2007, JOSA A 24, 2645): a Kalman filter per spatial
Fourier mode, with frozen-flow translation as its state model.

Choices (each a place where the actuator grid in a circular pupil departs from the paper's periodic square):

1. *Modes* (:class:`FourierBasis`): the pseudo-open-loop (POL) map on the active actuators is extended over an
   ``N x N`` periodic grid (``N`` the odd integer at or above ``padding`` times the actuators across: no Nyquist bin,
   so every mode's conjugate is another mode) by its biharmonic continuation (the smoothest fill: a sub-pixel
   Fourier shift of the extended map errs less than of the zero-padded one, ``docs/findings.md``), and
   ``rfft2`` gives ``M = N (N + 1) / 2`` complex modes (one of each conjugate pair). Back on the actuators:
   ``irfft2`` read at the active actuators. Forward then back is the identity on the actuators; back then forward
   is not: the modes are only approximately decoupled (the analysis treats them as decoupled, and the tests measure
   how well that holds).
2. *State* per mode ``k`` (cycles per metre): for each layer ``l`` (wind ``v_l``, weight ``w_l``) and each alias
   ``m`` (``|m_x|, |m_y| <= aliases``) a component at the true frequency ``k + m / pitch``, which frozen flow turns
   by ``a = alpha exp(-2 pi i (k + m / pitch).v_l T)`` per frame. The grid samples a field that is not band-limited
   (a subaperture mean is not), so the sampled mode is the sum of its aliases, each turning at its own rate:
   ``z_k = sum_s x_s + noise``. Innovation variance ``q_s = (1 - alpha²) S_k w_l P_km``: the mode's turbulence
   variance ``S_k`` (telemetry), split over layers by their weights and over aliases by the von Karman spectrum
   seen through the sensing kernel (known). Noise variance ``r_k``: the WFS noise through the mode's projection.
3. *Filter*: the stationary Kalman gain of each mode (closed form for one state, else the discrete algebraic
   Riccati equation by structure-preserving doubling, every mode at once); ``x(n|n) = A x(n-1|n-1) + K (z(n) -
   C A x(n-1|n-1))`` with ``z(n)`` the POL mode of frame ``n - d``; the command ``y(n) = -inverse(L x) /
   g_model`` with ``L = C A^d ((1 - f) I + f A)``: the turbulence predicted over the frames ``y(n)`` acts on (a
   fractional delay ``d + f`` as the LQG of :mod:`eofnn.control.classical` does).
4. *Piston, tip and tilt*: when the telemetry holds none (a simulation that removes them), they are projected out
   of the command; a frozen-flow shift of a PTT-free map is not PTT-free (projecting it out lowers the prediction
   error: ``docs/findings.md``).

What it reaches. With one state per mode (``aliases: 0``), a known wind and no noise, the Kalman gain is 1 and the
filter is the perfect sub-pixel shift of the extended map: its residual is the discretisation floor of frozen flow
on this grid, set by the sampled subaperture means that are not band-limited, by the fill outside the pupil that
does not move with the wind and by the piston, tip and tilt removed from each frame; the aliases in the state take
it below (``tests/test_pfc.py``: the floor below the integrator on the tiny 2 m scenario, the aliases below 0.65 of
it). Its margins (:mod:`eofnn.analysis.response`) take the modes as decoupled; how they compare with closing the
loop, and what it leaves on configs/realistic.yaml against the LQG and the integrator: ``docs/findings.md``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from eofnn.delay import split_delay
from eofnn.errors import ConfigError
from eofnn.resources import require_memory
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.loop.runner import LoopInput

DTYPE = torch.float64
CDTYPE = torch.complex128


def fft_size(n_across: int, padding: float) -> int:
    """The odd FFT size at or above ``padding * n_across``."""
    n = math.ceil(padding * n_across - 1e-9)
    return n + 1 - n % 2


def biharmonic_extension(mask: np.ndarray) -> np.ndarray:
    """``(outside, inside)`` matrix whose rows give each pixel outside ``mask`` (a periodic ``N x N`` map) as a
    combination of the pixels inside (row-major order): the solution of ``Laplacian² u = 0`` outside with the values
    inside fixed (the periodic 5-point Laplacian; positive definite outside when ``mask`` holds a pixel)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    n = mask.shape[0]
    one = sp.identity(n, format="csr")
    ring = sp.diags([1.0, 1.0, -2.0, 1.0, 1.0], [-(n - 1), -1, 0, 1, n - 1], shape=(n, n), format="csr")
    laplacian = (sp.kron(ring, one) + sp.kron(one, ring)).tocsr()
    operator = (laplacian @ laplacian).tocsr()
    inside = mask.ravel()
    block = operator[~inside]
    solve = splu(block[:, ~inside].tocsc())
    return -solve.solve(block[:, inside].toarray())


#: Largest size of the dense transforms (bytes) a basis keeps: below it, a frame's modes are two matrix products
#: (steady cost; small FFTs on a loaded machine vary widely: ``docs/findings.md``); above, extension and FFT.
DENSE_LIMIT_BYTES = 256 * 2**20


class FourierBasis:
    """The spatial Fourier modes of an actuator grid (module docstring, choice 1).

    ``forward(x)``: ``(..., K)`` actuator values to ``(..., M)`` complex modes (``rfft2`` of the extended map,
    unnormalised); ``inverse(a)``: back to ``(..., K)`` (``irfft2`` at the actuators: ``sum_k w_k Re(a_k
    exp(2 pi i k.x)) / N²``, ``w = 1`` on the ``k_x = 0`` column and 2 elsewhere). ``frequencies``: ``(M, 2)``
    ``(f_x, f_y)`` in cycles/m. Both maps are kept as dense matrices when they fit :data:`DENSE_LIMIT_BYTES`
    (``dense``), else computed by FFT; the two agree to rounding.
    """

    def __init__(self, grid: ActuatorGrid, padding: float = 2.0, dense: bool | None = None) -> None:
        self.grid, self.padding = grid, padding
        n, size = grid.n_across, fft_size(grid.n_across, padding)
        self.size = size
        offset = (size - n) // 2
        rows, cols = grid.indices.T
        self._pixels = torch.as_tensor((rows + offset) * size + cols + offset)
        mask = np.zeros((size, size), dtype=bool)
        mask.ravel()[self._pixels.numpy()] = True
        k = grid.n_actuators
        require_memory(8 * 3 * (size * size - k) * k, f"the Fourier modes' extension of {k} actuators over a "
                       f"{size} x {size} grid (pfc.padding={padding:g})")
        # The inside pixels in row-major order are the actuators in grid order (both row-major).
        self._outside = torch.as_tensor(np.flatnonzero(~mask))
        self._extension = torch.as_tensor(biharmonic_extension(mask)).T.contiguous()  # (K, outside)
        f_y = torch.fft.fftfreq(size, d=grid.pitch_m, dtype=DTYPE)
        f_x = torch.fft.rfftfreq(size, d=grid.pitch_m, dtype=DTYPE)
        self.frequencies = torch.stack(torch.broadcast_tensors(f_x.unsqueeze(0), f_y.unsqueeze(1)), -1).reshape(-1, 2)
        self.dense = 32 * k * self.n_modes <= DENSE_LIMIT_BYTES if dense is None else dense
        if self.dense:
            require_memory(32 * k * self.n_modes, f"the dense Fourier transforms of {k} actuators")
            eye = torch.eye(k, dtype=DTYPE)
            forward = torch.cat([self._fft_forward(eye[i: i + 256]) for i in range(0, k, 256)])  # (K, M)
            self._forward_re, self._forward_im = forward.real.contiguous(), forward.imag.contiguous()
            index = torch.arange(size, dtype=DTYPE)
            ky, kx = torch.meshgrid(index, index[: size // 2 + 1], indexing="ij")
            y, x = torch.as_tensor(rows + offset, dtype=DTYPE), torch.as_tensor(cols + offset, dtype=DTYPE)
            phase = 2 * math.pi / size * (ky.reshape(-1, 1) * y + kx.reshape(-1, 1) * x)  # (M, K)
            weight = (2.0 - (kx.reshape(-1, 1) == 0).to(DTYPE)) / size**2
            self._inverse_re, self._inverse_im = weight * torch.cos(phase), -weight * torch.sin(phase)

    @property
    def n_modes(self) -> int:
        return self.size * (self.size // 2 + 1)

    def extend(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., N, N)`` periodic maps of ``(..., K)`` actuator values (biharmonic outside the pupil)."""
        out = torch.empty(*x.shape[:-1], self.size * self.size, dtype=x.dtype)
        out[..., self._pixels] = x
        out[..., self._outside] = x @ self._extension.to(x.dtype)
        return out.view(*x.shape[:-1], self.size, self.size)

    def _fft_forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.fft.rfft2(self.extend(x)).flatten(-2)

    def _fft_inverse(self, modes: torch.Tensor) -> torch.Tensor:
        half = modes.view(*modes.shape[:-1], self.size, self.size // 2 + 1)
        return torch.fft.irfft2(half, s=(self.size, self.size)).flatten(-2)[..., self._pixels]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.dense:
            return self._fft_forward(x.to(DTYPE))
        x = x.to(DTYPE)
        return torch.complex(x @ self._forward_re, x @ self._forward_im)  # real products: half a complex one

    def inverse(self, modes: torch.Tensor) -> torch.Tensor:
        if not self.dense:
            return self._fft_inverse(modes)
        return modes.real @ self._inverse_re + modes.imag @ self._inverse_im

    def noise_gain(self) -> torch.Tensor:
        """``(M,)`` variance of each mode per nm² of white noise on every actuator: ``sum_j |forward(e_j)|²``."""
        if self.dense:
            return (self._forward_re.pow(2) + self._forward_im.pow(2)).sum(0)
        eye = torch.eye(self.grid.n_actuators, dtype=DTYPE)
        return sum(self._fft_forward(eye[i: i + 256]).abs().pow(2).sum(0) for i in range(0, len(eye), 256))


def alias_offsets(aliases: int) -> torch.Tensor:
    """``(A, 2)`` integer offsets ``m`` with ``|m_x|, |m_y| <= aliases``, ``(0, 0)`` first."""
    span = range(-aliases, aliases + 1)
    offsets = sorted(((mx, my) for mx in span for my in span), key=lambda m: (m != (0, 0), m))
    return torch.tensor(offsets, dtype=DTYPE)


def state_frequencies(frequencies: torch.Tensor, aliases: int, pitch_m: float) -> torch.Tensor:
    """``(M, A, 2)`` true frequencies ``k + m / pitch`` of each mode's aliases (cycles/m)."""
    return frequencies.unsqueeze(1) + alias_offsets(aliases) / pitch_m


def stationary_gain(a: torch.Tensor, q: torch.Tensor, r: torch.Tensor,
                    iterations: int = 200) -> tuple[torch.Tensor, torch.Tensor]:
    """Stationary Kalman gain ``(M, S)`` and prior covariance ``(M, S, S)`` of ``x(n+1) = diag(a) x(n) + e``
    (``<e e^H> = diag(q)``), ``z = sum_s x_s + v`` (``<|v|²> = r``), per mode ``(a, q: (M, S); r: (M,))``.

    One state: the scalar Riccati equation ``P = |a|² P r / (P + r) + q`` in closed form,
    ``P = (q - (1 - |a|²) r + sqrt((q - (1 - |a|²) r)² + 4 q r)) / 2``. Several: the structure-preserving doubling
    algorithm on the filter form (as :func:`eofnn.control.kalman.kalman_gain`, complex). ``r`` is floored at
    ``1e-9`` of the mode's total ``q`` so that a noise-free mode stays solvable.
    """
    m, s = a.shape
    q = q.to(DTYPE)
    r = torch.maximum(r.to(DTYPE), 1e-9 * q.sum(1)).clamp(min=1e-300)
    if s == 1:
        b = q[:, 0] - (1 - a[:, 0].abs().pow(2)) * r
        prior = ((b + torch.sqrt(b.pow(2) + 4 * q[:, 0] * r)) / 2).to(CDTYPE).view(m, 1, 1)
    else:
        a_k = torch.diag_embed(a.conj().to(CDTYPE))  # control form: A_c = A^H, G = C^H C / r, H = Q
        g_k = torch.ones(m, s, s, dtype=CDTYPE) / r.view(m, 1, 1)
        h_k = torch.diag_embed(q.to(CDTYPE))
        eye = torch.eye(s, dtype=CDTYPE)
        for _ in range(iterations):
            w = eye + g_k @ h_k
            a_w = torch.linalg.solve(w, a_k, left=False)  # a_k w^-1
            h_next = h_k + a_k.mH @ torch.linalg.solve(w, h_k, left=False) @ a_k
            g_k = g_k + a_w @ g_k @ a_k.mH
            a_k = a_w @ a_k
            change = (h_next - h_k).abs().amax((1, 2)) <= 1e-13 * h_next.abs().amax((1, 2))
            h_k = h_next
            if bool(change.all()):
                break
        prior = 0.5 * (h_k + h_k.mH)
    column = prior.sum(-1)  # P C^H with C = ones
    gain = column / (column.sum(-1, keepdim=True).real + r.unsqueeze(1))
    return gain, prior


@dataclass
class FourierPredictor:
    """Predictive Fourier control: per mode a stationary Kalman filter of frozen flow (module docstring).

    Attributes
    ----------
    basis : FourierBasis
        The modes.
    transition : Tensor
        ``(M, S)`` complex diagonal of each mode's state transition ``A``.
    kalman_gain : Tensor
        ``(M, S)`` complex stationary gain ``K``.
    delay_frames : float
        Loop delay ``d + f`` the prediction is made for.
    dm_gain_model : float
        DM gain of the POL reconstruction and of the command.
    remove_ptt : bool
        Project piston, tip and tilt out of the command.
    info : dict
        What was identified (winds, weights, noise), for ``metrics.json``.
    """

    basis: FourierBasis
    transition: torch.Tensor
    kalman_gain: torch.Tensor
    delay_frames: int | float
    dm_gain_model: float = 1.0
    remove_ptt: bool = False
    info: dict | None = None

    @property
    def output_row(self) -> torch.Tensor:
        """``(M, S)``: ``L = C A^d ((1 - f) I + f A)``, the turbulence acting during frame ``n`` per state."""
        d, f = split_delay(self.delay_frames)
        return self.transition.pow(d) * ((1 - f) + f * self.transition)

    def reset(self, batch: int, n_actuators: int, delay_frames: int | float, dtype: torch.dtype) -> None:
        if n_actuators != self.basis.grid.n_actuators:
            raise ConfigError(f"the Fourier controller was built for {self.basis.grid.n_actuators} actuators but the "
                              f"loop has {n_actuators}")
        if float(delay_frames) != float(self.delay_frames):
            raise ConfigError(f"the Fourier controller was built for delay_frames={self.delay_frames} but the plant "
                              f"has delay_frames={delay_frames}")
        self._d, self._f = split_delay(delay_frames)
        self._state = torch.zeros(batch, *self.transition.shape, dtype=CDTYPE)
        self._row = self.output_row.to(CDTYPE)
        self._ptt = torch.as_tensor(self.basis.grid.ptt_basis(), dtype=dtype) if self.remove_ptt else None
        zeros = torch.zeros(batch, n_actuators, dtype=dtype)
        self._past = deque([zeros] * (self._d + 1), maxlen=self._d + 1)  # y(n-1), ..., y(n-d-1)

    def modal_step(self, z: torch.Tensor) -> torch.Tensor:
        """Update every mode's filter with ``z`` ``(batch, M)`` (POL modes of frame ``n - d``); the predicted modes
        ``L x(n-d|n-d)`` ``(batch, M)``."""
        predicted = self._state * self.transition
        innovation = z - predicted.sum(-1)
        self._state = predicted + self.kalman_gain * innovation.unsqueeze(-1)
        return (self._state * self._row).sum(-1)

    def step(self, inp: LoopInput) -> torch.Tensor:
        d, f = self._d, self._f
        applied = self._past[d - 1] if not f else (1 - f) * self._past[d - 1] + f * self._past[d]
        pol = inp.wfs - self.dm_gain_model * applied
        field = self.basis.inverse(self.modal_step(self.basis.forward(pol)))
        if self._ptt is not None:
            field = field - (field @ self._ptt) @ self._ptt.T
        y = -field / self.dm_gain_model
        self._past.appendleft(y)
        return y

    def polynomials(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Per mode ``(D, N)`` (complex, ``(M, L)``) with ``D(z) y = N(z) u`` on the reading ``u(n) = wfs(n - d)``,
        the modes taken as decoupled.

        From the POL mode to the command the filter is ``W = N_w / D_w`` with ``F = (I - K C) A = A - K (C A)``, a
        diagonal plus rank one: with ``Delta = prod_s (1 - a_s z^-1)`` and ``Delta_s = Delta / (1 - a_s z^-1)``,
        ``D_w = det(I - z^-1 F) = Delta + z^-1 sum_s a_s K_s Delta_s`` (matrix determinant lemma) and
        ``N_w = -sum_s L_s K_s Delta_s / g_model`` (Sherman-Morrison); the POL coupling then gives ``D = D_w +
        g_model z^-d H N_w``, ``N = N_w`` (as :meth:`eofnn.control.classical.ModalLQG.polynomials`). With many
        states the coefficients hold the loop only to rounding near the states' poles: the analysis reads
        :meth:`frequency_response` and :meth:`closed_loop_moduli` instead.
        """
        a, k, row = self.transition.to(CDTYPE), self.kalman_gain.to(CDTYPE), self.output_row.to(CDTYPE)
        m, s = a.shape
        factors = torch.stack([torch.ones_like(a), -a], -1)  # (M, S, 2): 1 - a_s z^-1
        partial = []
        for i in range(s):
            p = torch.ones(m, 1, dtype=CDTYPE)
            for j in range(s):
                if j != i:
                    p = _multiply(p, factors[:, j])
            partial.append(p)
        partial = torch.stack(partial, 1)  # (M, S, S): Delta_s
        full = _multiply(partial[:, 0], factors[:, 0])
        d_w = _add(full, torch.cat([torch.zeros(m, 1, dtype=CDTYPE), ((a * k).unsqueeze(-1) * partial).sum(1)], 1))
        n_w = -((row * k).unsqueeze(-1) * partial).sum(1) / self.dm_gain_model
        d, f = split_delay(self.delay_frames)
        response = torch.zeros(d + 2, dtype=CDTYPE)
        response[d], response[d + 1] = 1 - f, f
        return _add(d_w, self.dm_gain_model * _multiply(n_w, response.expand(m, -1))), n_w

    @cached_property
    def _residues(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(a (M, S), [K_s L_s, K_s a_s] (M, S, 2))``: the poles and residues of :meth:`frequency_response`."""
        a, k = self.transition.to(CDTYPE), self.kalman_gain.to(CDTYPE)
        return a, torch.stack([k * self.output_row.to(CDTYPE), k * a], -1)

    def frequency_response(self, omega: torch.Tensor, rows: torch.Tensor | None = None) -> tuple[torch.Tensor,
                                                                                                  torch.Tensor]:
        """``(D / Delta, N / Delta)`` of :meth:`polynomials` at ``z = exp(i omega)``, ``(R, F)`` for modes ``rows``
        (all by default) and ``omega`` ``(R or 1, F)`` rad/frame, by partial fractions: ``N / Delta = -sum_s L_s K_s /
        (1 - a_s z^-1) / g_model``, ``D / Delta = 1 + z^-1 sum_s a_s K_s / (1 - a_s z^-1) + g_model z^-d H N /
        Delta``. Dividing by ``Delta = prod_s (1 - a_s z^-1)`` changes no ratio of the loop (crossings, transfer
        functions), and spares the products of 18 factors that vanish near the states' cluster of turning rates,
        where the coefficients of the polynomials leave nothing but rounding (``docs/findings.md``)."""
        a, residues = self._residues
        if rows is not None:
            a, residues = a[rows], residues[rows]
        z_inv = torch.exp(-1j * omega.to(DTYPE))  # (R, F)
        sums = (1 / (1 - a.unsqueeze(1) * z_inv.unsqueeze(-1))) @ residues  # (R, F, 2)
        n = -sums[..., 0] / self.dm_gain_model
        d, f = split_delay(self.delay_frames)
        return 1 + z_inv * sums[..., 1] + self.dm_gain_model * z_inv**d * ((1 - f) + f * z_inv) * n, n

    def closed_loop_moduli(self, dm_gain: float = 1.0, wfs_gain: float = 1.0,
                           plant_delay_frames: float | None = None) -> torch.Tensor:
        """``(M,)`` largest closed-loop pole modulus of each mode's loop (modes taken as decoupled), from its state
        space: the roots of the characteristic polynomial of :meth:`polynomials` are clustered near ``alpha`` on
        the circle and too ill-conditioned at 18 states to tell 0.9998 from 1.0001; these eigenvalues are not.

        With the plant delay ``d_p + f_p`` and the controller's ``d + f``, the POL mode the filter reads is ``z(n) =
        sum_j c_j y(n - j)``, ``c = w g h_p - g_model h_c`` (``h`` the DM responses ``z^-d ((1 - f) + f z^-1)``);
        the state ``[x(n), y(n), ..., y(n - D + 1)]`` evolves by ``x(n) = F x(n-1) + K c.y``, ``y(n) = -L x(n) /
        g_model``.
        """
        plant = self.delay_frames if plant_delay_frames is None else plant_delay_frames
        a, k, row = self.transition.to(CDTYPE), self.kalman_gain.to(CDTYPE), self.output_row.to(CDTYPE)
        m, s = a.shape
        lags = max(split_delay(plant)[0], split_delay(self.delay_frames)[0]) + 1
        c = torch.zeros(lags + 1, dtype=DTYPE)  # c[j]: coefficient of y(n - j)
        for delay, scale in ((plant, wfs_gain * dm_gain), (self.delay_frames, -self.dm_gain_model)):
            d, f = split_delay(delay)
            c[d] += scale * (1 - f)
            c[d + 1] += scale * f
        c = c[1:].to(CDTYPE)
        f_mat = torch.diag_embed(a) - k.unsqueeze(-1) * a.unsqueeze(-2)
        out = -row.unsqueeze(1) / self.dm_gain_model  # (M, 1, S)
        system = torch.zeros(m, s + lags, s + lags, dtype=CDTYPE)
        system[:, :s, :s] = f_mat
        system[:, :s, s:] = k.unsqueeze(-1) * c
        system[:, s: s + 1, :s] = out @ f_mat
        system[:, s, s:] = (out @ k.unsqueeze(-1)).view(m, 1) * c
        system[:, s + 1:, s: -1] = torch.eye(lags - 1, dtype=CDTYPE)
        return torch.linalg.eigvals(system).abs().amax(-1)


def _multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise product of complex polynomials in ``z^-1`` (``(M, La)``, ``(M, Lb)``)."""
    out = torch.zeros(a.shape[0], a.shape[1] + b.shape[1] - 1, dtype=CDTYPE)
    for j in range(b.shape[1]):
        out[:, j: j + a.shape[1]] += a * b[:, j: j + 1]
    return out


def _add(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    n = max(a.shape[1], b.shape[1])
    return torch.nn.functional.pad(a, (0, n - a.shape[1])) + torch.nn.functional.pad(b, (0, n - b.shape[1]))
