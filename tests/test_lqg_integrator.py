"""The LQG with the integrator's model: a random-walk turbulence model per mode (AR(1) with ``a1 = 1``) and white
noise. Its stationary Kalman gain ``k`` solves ``P² / (P + r) = q``; the LQG then reproduces, command for command,

- at a one-frame delay the integrator of gain ``k`` (``y(n) = y(n-1) - k wfs(n-1)``): the integrator is a special
  case of the LQG there;
- at a two-frame delay not the integrator but the pseudo-open-loop integrator ``y(n) = (1 - k) y(n-1) + k y(n-2) -
  k wfs(n-2)`` (the Kalman filter's innovation uses its latest estimate, the integrator's the one applied ``d``
  frames ago): there no LQG of this family is the integrator, and the LQG may lose to it.
"""

from __future__ import annotations

import math

import pytest
import torch

from eofnn.control.baselines import Integrator
from eofnn.control.classical import ModalLQG
from eofnn.control.kalman import kalman_gain
from eofnn.sim.loop.runner import LoopInput

F64 = torch.float64


def random_walk_lqg(k: int, q: float, r: float, delay: int) -> tuple[ModalLQG, float]:
    """The LQG of ``k`` modes (the identity as modes), each a random walk of innovation ``q`` seen with noise ``r``
    (nm²), and its Kalman gain."""
    ar = torch.tensor([[1.0, 0.0]], dtype=F64).repeat(k, 1)
    qs, rs = torch.full((k,), q, dtype=F64), torch.full((k,), r, dtype=F64)
    gain, _ = kalman_gain(ar, qs, rs)
    return ModalLQG(torch.eye(k, dtype=F64), ar, qs, rs, gain, delay), float(gain[0, 0])


def close_loop(controller, delay: int, frames: int = 300, k: int = 5, seed: int = 0) -> torch.Tensor:
    """Commands ``(frames, k)`` of ``controller`` in a loop ``wfs(n) = s(n) + y(n) + v(n)`` whose reading reaches it
    ``delay`` frames later (s: a random walk plus a sine, v: white noise; one realisation)."""
    gen = torch.Generator().manual_seed(seed)
    s = torch.randn(frames, k, generator=gen, dtype=F64).cumsum(0) * 3.0
    s += 20 * torch.sin(torch.arange(frames, dtype=F64) / 7.0).unsqueeze(1)
    noise = torch.randn(frames, k, generator=gen, dtype=F64)
    controller.reset(1, k, delay, F64)
    wfs, commands = torch.zeros(frames, k, dtype=F64), torch.zeros(frames, k, dtype=F64)
    for n in range(frames):
        seen = wfs[n - delay] if n >= delay else torch.zeros(k, dtype=F64)
        commands[n] = controller.step(LoopInput(n, seen.unsqueeze(0), torch.zeros(1, k, dtype=F64)))[0]
        wfs[n] = s[n] + commands[n] + noise[n]
    return commands


@pytest.mark.parametrize("q, r", [(1.0, 1.0), (1.0, 10.0), (5.0, 0.5)])
def test_the_random_walk_kalman_gain_is_the_riccati_solution(q, r):
    p = (q + math.sqrt(q * q + 4 * q * r)) / 2
    _, k = random_walk_lqg(3, q, r, 1)
    assert k == pytest.approx(p / (p + r), rel=1e-10)


@pytest.mark.parametrize("q, r", [(1.0, 1.0), (1.0, 10.0), (5.0, 0.5)])
def test_at_one_frame_of_delay_the_lqg_with_the_integrators_model_is_the_integrator(q, r):
    lqg, k = random_walk_lqg(5, q, r, 1)
    assert torch.allclose(close_loop(lqg, 1), close_loop(Integrator(k), 1), rtol=1e-9, atol=1e-9)


class PolIntegrator:
    """``y(n) = (1 - k) y(n-1) + k y(n-2) - k wfs(n-2)``: the integrator of the pseudo-open-loop signal."""

    def __init__(self, gain: float) -> None:
        self.gain = gain

    def reset(self, batch, n_actuators, delay_frames, dtype) -> None:
        self._y = [torch.zeros(batch, n_actuators, dtype=dtype)] * 2

    def step(self, inp: LoopInput) -> torch.Tensor:
        y = (1 - self.gain) * self._y[0] + self.gain * self._y[1] - self.gain * inp.wfs
        self._y = [y, self._y[0]]
        return y


def test_at_two_frames_of_delay_it_is_the_pol_integrator_not_the_integrator():
    lqg, k = random_walk_lqg(5, 1.0, 1.0, 2)
    commands = close_loop(lqg, 2)
    assert torch.allclose(commands, close_loop(PolIntegrator(k), 2), rtol=1e-9, atol=1e-9)
    assert not torch.allclose(commands, close_loop(Integrator(k), 2), rtol=1e-3, atol=1e-3)
