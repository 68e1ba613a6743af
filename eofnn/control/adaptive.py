"""Controllers that adapt a per-actuator linear filter from telemetry while the loop runs.

Both learn the regression a fitted EOF filter solves, built from telemetry alone: at frame ``n`` the WFS reading
of frame ``n - d`` arrives, so its pseudo-open-loop value ``s_hat(n - d) = wfs(n - d) - g_model y(n - d)`` is known,
and ``-s_hat(n - d) / g_model`` is the command that would have cancelled frame ``n - d``. It is regressed on the
history the controller had for that frame (``d`` frames ago), closed-loop or open-loop as in
:mod:`eofnn.data.history`.

- :class:`RLSController`: recursive least squares, one batched rank-1 update of ``(K, taps, taps)`` inverse
  covariances per frame, with a forgetting factor.
- :class:`BlendController`: every ``every_frames`` frames, a ridge fit on the last ``window_frames`` frames
  (normal equations kept per block of ``every_frames`` frames), blended into the running filter.

A safe fallback guards both: when the measured residual RMS exceeds ``fallback_factor`` times its running median
or twice the uncorrected RMS (measured while the first commands were zero), or the filter or command is not
finite, that realisation switches to an integrator restarted from zero for good, and the frame is recorded in
:attr:`AdaptiveController.fallback_frames`; the loop never raises.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections import deque

import torch

from eofnn.control.predictive import HistoryRing
from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError, require
from eofnn.seeding import torch_generator
from eofnn.sim.loop.runner import LoopInput
from eofnn.validation import COUNT, FINITE, FRACTION, NON_NEGATIVE, POSITIVE, Interval, check_value

#: Controlled frames before the fallback's running median is trusted.
ARM_FRAMES = 10
#: A measured residual RMS above this times the uncorrected one triggers the fallback at once.
OPEN_LOOP_FACTOR = 2.0
#: Frames between refreshes of slow checks: the RLS covariance trace cap (growth under forgetting is lambda^-n),
#: the running median of the residual RMS once its window is full, the finiteness of the filter weights.
CHECK_FRAMES = 16


def integrator_filter(spec: HistorySpec, gain: float, leak: float = 0.0) -> torch.Tensor:
    """``(1, taps)`` weights equivalent to the simplest controller of a history kind.

    Closed loop: the leaky integrator ``y(n) = (1 - leak) y(n-1) - gain wfs(n-d)``. Open loop:
    ``y(n) = -gain s_hat(n-d)`` (the pseudo-open-loop integrator: with ``gain = 1``, perfect correction ``d`` frames
    late; ``leak`` does not apply). ``gain >= 0`` and ``leak`` in [0, 1], as the controller's config (or the
    adaptive controller's own arguments) checked them.
    """
    weights = torch.zeros(1, spec.n_taps, dtype=torch.float64)
    if spec.kind == "closed_loop":
        weights[0, 0], weights[0, spec.history_length] = 1.0 - leak, -gain
    else:
        weights[0, 0] = -gain
    return weights


class AdaptiveController(ABC):
    """Shared machinery: histories, the telemetry regression pairs, dither and the fallback.

    Parameters
    ----------
    spec : HistorySpec
        History kind, length and the loop delay.
    initial_weights : Tensor, optional
        ``(K, taps)`` or ``(1, taps)`` starting filter (e.g. a fitted ``LinearFilter.weight``); if not given, the
        integrator-equivalent :func:`integrator_filter` (closed loop: the integrator of ``integrator_gain``; open
        loop: the pseudo-open-loop integrator ``-s_hat(n-d)``).
    dm_gain_model : float
        DM gain assumed in the pseudo-open-loop reconstruction and the target.
    dither_nm : float
        RMS of white dither added to every command (excitation for closed-loop identification), nm.
    integrator_gain : float
        Gain of the integrator used to start from (if no weights) and to fall back to.
    fallback_factor : float
        Residual RMS above this times its running median for ``fallback_patience`` frames in a row triggers the
        fallback.
    fallback_patience : int, optional
        Consecutive frames above ``fallback_factor`` times the median that trigger the fallback; by default
        ``2 (history_length + delay_frames)``, so that a jump of the turbulence (which leaves the history after
        ``history_length + delay_frames`` frames) does not.
    median_frames : int
        Frames of measured residual RMS in the running median (armed after :data:`ARM_FRAMES` controlled frames).
    seed : int
        Seed of the dither.
    """

    def __init__(self, spec: HistorySpec, initial_weights: torch.Tensor | None = None, *, dm_gain_model: float = 1.0,
                 dither_nm: float = 0.0, integrator_gain: float = 0.5, fallback_factor: float = 10.0,
                 fallback_patience: int | None = None, median_frames: int = 200, seed: int = 0) -> None:
        require(isinstance(spec, HistorySpec), f"spec must be a HistorySpec, got {type(spec).__name__}")
        require(not spec.delay_fraction, f"delay_frames={spec.delay_frames} is invalid for an adaptive controller: "
                "it supports integer delays only")
        check_value("dm_gain_model", dm_gain_model, FINITE)
        require(dm_gain_model != 0, "dm_gain_model=0 is invalid: it must be non-zero")
        check_value("dither_nm", dither_nm, Interval(0, None, unit="nm"))
        check_value("integrator_gain", integrator_gain, NON_NEGATIVE)
        check_value("fallback_factor", fallback_factor, Interval(1, None, closed="neither"))
        if fallback_patience is None:
            fallback_patience = 2 * (spec.history_length + spec.delay_frames)
        check_value("fallback_patience", fallback_patience, COUNT)
        check_value("median_frames", median_frames, COUNT)
        check_value("seed", seed, Interval(0, 2**63 - 1, integer=True))
        if initial_weights is not None:
            initial_weights = initial_weights.detach().to(torch.float64).cpu()
            require(initial_weights.dim() == 2 and initial_weights.shape[1] == spec.n_taps,
                    f"initial_weights of shape {tuple(initial_weights.shape)} do not fit {spec.n_taps} taps per actuator "
                    "(expected (K, taps) or (1, taps))")
            require(bool(torch.isfinite(initial_weights).all()), "initial_weights hold non-finite values")
        self.spec, self.initial_weights, self.dm_gain_model = spec, initial_weights, dm_gain_model
        self.dither_nm, self.integrator_gain, self.seed = dither_nm, integrator_gain, seed
        self.fallback_factor, self.fallback_patience, self.median_frames = fallback_factor, fallback_patience, median_frames

    # -- the protocol of eofnn.sim.loop.runner ------------------------------------------------------------------------
    def reset(self, batch: int, n_actuators: int, delay_frames: int, dtype: torch.dtype) -> None:
        if delay_frames != self.spec.delay_frames:
            raise ConfigError(f"adaptive controller is set up for delay_frames={self.spec.delay_frames} but the plant "
                              f"has delay_frames={delay_frames}")
        start = self.initial_weights if self.initial_weights is not None else \
            integrator_filter(self.spec, self.integrator_gain if self.spec.kind == "closed_loop" else 1.0)
        require(start.shape[0] in (1, n_actuators),
                f"initial_weights have {start.shape[0]} rows but the loop has n_actuators={n_actuators}")
        p, d, taps = self.spec.history_length, self.spec.delay_frames, self.spec.n_taps
        shape = (batch, n_actuators)
        self.weights = start.expand(n_actuators, taps).repeat(batch, 1, 1).contiguous()  # (B, K, taps)
        self._y = HistoryRing(shape, max(p, d), torch.float64)
        self._signal = HistoryRing(shape, p, torch.float64)
        self._regressors = torch.zeros(d, batch, n_actuators, taps, dtype=torch.float64)  # slot n % d: x(n - d)
        self._rms = torch.zeros(self.median_frames, batch, dtype=torch.float64)
        self.fallback_frames = torch.full((batch,), -1, dtype=torch.int64)
        self._fallback_y = torch.zeros(shape, dtype=torch.float64)
        self._high_frames = torch.zeros(batch, dtype=torch.int64)
        self._open_loop_sum = torch.zeros(batch, dtype=torch.float64)
        self._open_loop_rms = torch.full((batch,), math.inf, dtype=torch.float64)
        self._frames_seen, self._out_dtype = 0, dtype
        self._gen = torch_generator(self.seed, "adaptive-dither")
        self._reset_learning(batch, n_actuators, taps)

    @torch.no_grad()
    def step(self, inp: LoopInput) -> torch.Tensor:
        p, d = self.spec.history_length, self.spec.delay_frames
        n, frame = self._frames_seen, inp.frame
        wfs = inp.wfs.to(torch.float64)
        self._measure_open_loop(wfs)
        s_hat = wfs - self.dm_gain_model * self._y[d - 1]  # POL value of frame n - d
        if self.spec.kind == "open_loop":
            self._signal.push(s_hat)
            history = self._signal.view
        else:
            self._signal.push(wfs)
            history = torch.cat([self._y.view[..., :p], self._signal.view], dim=-1)
        slot = n % d
        if n >= self.spec.first_frame + d:  # the history of frame n - d was a true one: learn from it
            self._learn(self._regressors[slot], -s_hat / self.dm_gain_model, frame)
        self._regressors[slot] = history
        if n < self.spec.first_frame:
            y = torch.zeros_like(wfs)
        else:
            y = (self.weights * history).sum(-1)
            y = self._guard(y, wfs, frame)
        if self.dither_nm:
            y = y + self.dither_nm * torch.randn(y.shape, generator=self._gen, dtype=torch.float64)
        self._frames_seen += 1
        self._y.push(y)
        return y.to(self._out_dtype)

    # -- fallback ------------------------------------------------------------------------------------------------
    @property
    def fallback_frame(self) -> int | None:
        """First frame at which any realisation fell back to the integrator (``None``: never)."""
        hit = self.fallback_frames[self.fallback_frames >= 0]
        return int(hit.min()) if len(hit) else None

    def _guard(self, y: torch.Tensor, wfs: torch.Tensor, frame: int) -> torch.Tensor:
        """Replace the command by the integrator's for realisations that fell back (now or before)."""
        controlled = self._frames_seen - self.spec.first_frame  # frames with a command from the filter before
        rms = wfs.pow(2).mean(-1).sqrt()
        # A sum is finite only if every term is: one reduction instead of an elementwise test.
        bad = ~torch.isfinite(y.sum(-1)) | ~torch.isfinite(rms)
        if self._frames_seen % CHECK_FRAMES == 0:
            bad |= ~torch.isfinite(self.weights.sum((-1, -2)))
        # Worse than no correction at all (twice the RMS measured while the commands were zero): diverging.
        bad |= rms > OPEN_LOOP_FACTOR * self._open_loop_rms
        filled = min(controlled, self.median_frames)
        if filled >= ARM_FRAMES:  # the median covers controlled frames only: not the uncorrected start
            if filled < self.median_frames or controlled % CHECK_FRAMES == 0:  # a slow statistic: refresh it now and then
                self._median = self._rms[:filled].median(0).values
            high = rms > self.fallback_factor * self._median
            # Persistently high, not a transient (a jump in the turbulence passes once the history has renewed).
            self._high_frames = torch.where(high, self._high_frames + 1, 0)
            bad |= self._high_frames >= self.fallback_patience
        self._rms[controlled % self.median_frames] = torch.where(torch.isfinite(rms), rms, 0.0)
        newly = bad & (self.fallback_frames < 0)
        self.fallback_frames[newly] = frame
        fallen = self.fallback_frames >= 0
        if not bool(fallen.any()):
            return y
        # The integrator restarts from a zero command: the diverging commands are dropped, not integrated on.
        self._fallback_y = torch.where(newly.unsqueeze(-1), 0.0, self._fallback_y) - self.integrator_gain * wfs
        return torch.where(fallen.unsqueeze(-1), self._fallback_y, y)

    def _measure_open_loop(self, wfs: torch.Tensor) -> None:
        """Mean RMS of the readings of frames commanded with zeros (frames d .. first_frame + d - 1)."""
        n, d = self._frames_seen, self.spec.delay_frames
        if d <= n < self.spec.first_frame + d:
            self._open_loop_sum += wfs.pow(2).mean(-1).sqrt()
            self._open_loop_rms = self._open_loop_sum / (n - d + 1)

    # -- learning (subclasses) -----------------------------------------------------------------------------------
    @abstractmethod
    def _reset_learning(self, batch: int, n_actuators: int, taps: int) -> None:
        """Clear what the filter has learnt (RLS covariances, blend normal equations) for a new run."""

    @abstractmethod
    def _learn(self, regressor: torch.Tensor, target: torch.Tensor, frame: int) -> None:
        """Update the filter with one frame's ``(batch, K, taps)`` regressor and ``(batch, K)`` target."""


class RLSController(AdaptiveController):
    """Recursive least squares per actuator, batched over actuators (and realisations).

    Per frame, with regressor ``x`` and target ``t`` of each actuator: ``k = P x / (lambda + x' P x)``,
    ``w += k (t - w' x)``, ``P = (P - k x' P) / lambda``. The starting filter counts as ``prior_frames`` frames of
    data (``P_0 = I / (prior_frames * mean x^2)`` from the first regressor), and ``trace(P)`` is capped at
    ``trace_cap`` times its starting value so that directions the data does not excite cannot wind up without bound
    under forgetting.

    Parameters
    ----------
    forgetting : float
        Forgetting factor ``lambda`` in (0, 1]: the memory is about ``1 / (1 - lambda)`` frames.
    prior_frames : float
        Weight of the starting filter, in frames of data.
    trace_cap : float
        Cap of ``trace(P)`` relative to ``trace(P_0)``. Turbulence histories are smooth, so their covariance has
        eigenvalues 1e-6 of its mean and below: a cap near 1 would act as a strong ridge on exactly the directions
        that fine prediction needs.
    **kwargs
        See :class:`AdaptiveController`.
    """

    def __init__(self, spec: HistorySpec, initial_weights: torch.Tensor | None = None, *, forgetting: float = 0.999,
                 prior_frames: float = 1.0, trace_cap: float = 1e8, **kwargs) -> None:
        check_value("forgetting", forgetting, FRACTION)
        check_value("prior_frames", prior_frames, POSITIVE)
        check_value("trace_cap", trace_cap, Interval(1, None))
        super().__init__(spec, initial_weights, **kwargs)
        self.forgetting, self.prior_frames, self.trace_cap = float(forgetting), float(prior_frames), float(trace_cap)

    def _reset_learning(self, batch: int, n_actuators: int, taps: int) -> None:
        # P = scale * Q: the division by lambda every frame only touches the scalar (one pass less over Q).
        # Q is stored (taps, taps, B * K), actuators last, so that every operation runs along contiguous memory.
        self._q: torch.Tensor | None = None  # set from the first regressor
        self._scale = 1.0
        self._trace_cap: torch.Tensor | None = None
        self._updates = 0

    @property
    def covariance(self) -> torch.Tensor | None:
        """The inverse covariance matrices ``P``, ``(B * K, taps, taps)`` (``None`` before the first update)."""
        return None if self._q is None else (self._scale * self._q).permute(2, 0, 1)

    def _learn(self, regressor: torch.Tensor, target: torch.Tensor, frame: int) -> None:
        self.update(regressor, target)

    def update(self, regressor: torch.Tensor, target: torch.Tensor) -> None:
        """One RLS step for all actuators: ``regressor (B, K, taps)``, ``target (B, K)``."""
        taps = regressor.shape[-1]
        x = regressor.reshape(-1, taps)
        x_t = x.T.contiguous()  # (taps, B * K)
        if self._q is None:
            power = x.pow(2).mean(-1).clamp(min=torch.finfo(torch.float64).tiny)
            start = 1.0 / (self.prior_frames * power)
            self._q = torch.eye(taps, dtype=torch.float64, device=x.device).unsqueeze(-1) * start
            self._scale, self._trace_cap = 1.0, self.trace_cap * taps * start
        px = (self._q * x_t).sum(1).mul_(self._scale)  # (P x)_i = sum_j P_ij x_j
        gain = px / (self.forgetting + (x_t * px).sum(0))
        w = self.weights.view(-1, taps)
        error = target.reshape(-1) - (w * x).sum(-1)
        w.addcmul_(gain.T, error.unsqueeze(-1))
        # P <- (P - k (P x)') / lambda, as Q <- Q - k (P x)' / scale and scale <- scale / lambda: one pass over Q.
        self._q.addcmul_(gain.unsqueeze(1), px.unsqueeze(0), value=-1.0 / self._scale)
        self._scale /= self.forgetting
        self._updates += 1
        if self.forgetting < 1 and self._updates % CHECK_FRAMES == 0:
            trace = self._scale * self._q.diagonal(dim1=0, dim2=1).sum(-1)
            over = trace > self._trace_cap
            if bool(over.any()):
                self._q[..., over] *= self._trace_cap[over] / trace[over]
            if self._scale > 1e100:  # fold the scalar back long before it could overflow
                self._q.mul_(self._scale)
                self._scale = 1.0


class BlendController(AdaptiveController):
    """Periodic ridge refit on a sliding window, blended into the running filter (recompute-and-blend).

    Normal equations ``sum x x'`` and ``sum x t`` are accumulated per actuator over blocks of ``every_frames``
    frames; at the end of each block the last ``window_frames`` frames (whole blocks) are solved with a relative
    ridge ``alpha`` and the filter becomes ``(1 - gain) W + gain W_new``. The solve is a minimal batched Cholesky
    here (``eofnn.training.ridge`` sits above the controllers in the layering).

    Parameters
    ----------
    every_frames : int
        Frames between refits.
    window_frames : int
        Frames of telemetry in each refit (rounded up to whole blocks of ``every_frames``).
    gain : float
        Blend gain in (0, 1].
    alpha : float
        Ridge parameter relative to the mean diagonal of ``sum x x'``.
    **kwargs
        See :class:`AdaptiveController`.
    """

    def __init__(self, spec: HistorySpec, initial_weights: torch.Tensor | None = None, *, every_frames: int = 500,
                 window_frames: int = 2000, gain: float = 0.2, alpha: float = 1e-6, **kwargs) -> None:
        check_value("every_frames", every_frames, COUNT)
        check_value("window_frames", window_frames, Interval(every_frames, None, integer=True, unit="frames"))
        check_value("gain", gain, FRACTION, where="blend ")
        check_value("alpha", alpha, NON_NEGATIVE)
        super().__init__(spec, initial_weights, **kwargs)
        self.every_frames, self.gain, self.alpha = every_frames, float(gain), float(alpha)
        self.window_blocks = -(-window_frames // every_frames)
        self.refits = 0

    def _reset_learning(self, batch: int, n_actuators: int, taps: int) -> None:
        self._gram = torch.zeros(batch * n_actuators, taps, taps, dtype=torch.float64)
        self._cross = torch.zeros(batch * n_actuators, taps, dtype=torch.float64)
        self._block_frames = 0
        self._blocks: deque[tuple[torch.Tensor, torch.Tensor]] = deque(maxlen=self.window_blocks)
        self.refits = 0

    def _learn(self, regressor: torch.Tensor, target: torch.Tensor, frame: int) -> None:
        x = regressor.reshape(-1, regressor.shape[-1])
        self._gram.baddbmm_(x.unsqueeze(-1), x.unsqueeze(1))
        self._cross.addcmul_(x, target.reshape(-1, 1))
        self._block_frames += 1
        if self._block_frames == self.every_frames:
            self._blocks.append((self._gram.clone(), self._cross.clone()))
            self._gram.zero_()
            self._cross.zero_()
            self._block_frames = 0
            self._refit()

    def _refit(self) -> None:
        gram = sum(block[0] for block in self._blocks)
        cross = sum(block[1] for block in self._blocks)
        taps = gram.shape[-1]
        scale = gram.diagonal(dim1=1, dim2=2).mean(-1).clamp(min=torch.finfo(torch.float64).tiny)
        regularised = gram + (self.alpha * scale).view(-1, 1, 1) * torch.eye(taps, dtype=torch.float64)
        chol, info = torch.linalg.cholesky_ex(regularised)
        solution = torch.cholesky_solve(cross.unsqueeze(-1), chol).squeeze(-1)
        ok = (info == 0) & torch.isfinite(solution).all(-1)  # a singular group keeps its filter
        w = self.weights.view(-1, taps)
        w[ok] = (1 - self.gain) * w[ok] + self.gain * solution[ok]
        self.refits += 1
