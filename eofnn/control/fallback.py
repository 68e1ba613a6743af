"""The integrator on the modes where a predictor does not beat it: the composite a per-mode fallback deploys
(:mod:`eofnn.evaluation.fallback` decides the modes).

Per frame, both read the same measurement ``m = wfs(n - d)``:

    i(n) = y(n-1) - gain m            the integrator, on the command really applied
    p(n)                              the predictor's command
    y(n) = i(n) + B Bᵀ (p(n) - i(n))  (``B``: ``(K, M)`` orthonormal columns, the modes the predictor keeps)

or, on actuators, ``y_k(n) = p_k(n)`` where the predictor keeps actuator ``k`` and ``i_k(n)`` elsewhere. The
predictor is then told the command applied (``applied(y)``), so its closed-loop taps and pseudo-open-loop
reconstruction read what the loop did, as they read telemetry when they were fitted. On the modes it keeps, the
loop is the predictor's; on the others, the integrator's.
"""

from __future__ import annotations

import torch

from eofnn.errors import require
from eofnn.sim.loop.runner import Controller, LoopInput
from eofnn.validation import Interval, check_value


class ModalFallback:
    """A predictor on some modes, the integrator of ``gain`` on the rest (module docstring).

    Parameters
    ----------
    predictor : Controller
        The predictor's controller (a :class:`~eofnn.control.predictive.PredictiveController`: it has
        ``applied``).
    gain : float
        The integrator's gain.
    kept : Tensor
        ``(K, M)`` orthonormal columns spanning the modes the predictor commands, or a ``(K,)`` boolean mask of the
        actuators it commands.
    """

    def __init__(self, predictor: Controller, gain: float, kept: torch.Tensor) -> None:
        check_value("integrator gain", gain, Interval(0, 10))
        require(hasattr(predictor, "applied"), f"a per-mode fallback needs a predictor that reads back the command "
                                               f"applied; {type(predictor).__name__} does not")
        require(kept.dim() in (1, 2), f"kept modes of shape {tuple(kept.shape)} are invalid: (K, M) or (K,)")
        self.predictor, self.gain = predictor, float(gain)
        self._mask = kept.to(torch.bool) if kept.dim() == 1 else None
        self._basis = None if kept.dim() == 1 else kept.to(torch.float64)

    def reset(self, batch: int, n_actuators: int, delay_frames: int | float, dtype: torch.dtype) -> None:
        kept = self._mask if self._mask is not None else self._basis
        require(kept.shape[0] == n_actuators, f"the fallback's modes span {kept.shape[0]} actuators, the loop has "
                                              f"{n_actuators}")
        self.predictor.reset(batch, n_actuators, delay_frames, dtype)
        self._last = torch.zeros(batch, n_actuators, dtype=dtype)
        if self._basis is not None:
            self._projector = (self._basis @ self._basis.T).to(dtype)

    def step(self, inp: LoopInput) -> torch.Tensor:
        predicted = self.predictor.step(inp)
        integrated = self._last - self.gain * inp.wfs
        if self._mask is not None:
            y = torch.where(self._mask, predicted, integrated)
        else:
            y = integrated + (predicted - integrated) @ self._projector
        self.predictor.applied(y)
        self._last = y
        return y
