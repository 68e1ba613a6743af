"""Sensing kernels: what one actuator's sensor reads of the phase screen, as a transfer function on its spectrum.

The Fourier syntheses of :mod:`eofnn.sim.atmosphere` build each layer from its spectrum, so a linear sensor is a
multiplication in the Fourier domain, exact, with no interpolation:

- ``subaperture``: the mean of the phase over the actuator's ``d x d`` subaperture (``d`` = pitch),
  ``H(f_x, f_y) = sinc(d f_x) sinc(d f_y)`` in telescope-frame frequencies (cycles per metre; ``sinc(x) =
  sin(pi x) / (pi x)``). A perfect zonal Shack-Hartmann-like measurement: no slopes, no aliasing into the
  reconstruction, no photon noise. Its zeros put true nulls in a layer's temporal PSD at multiples of ``v / d``.
- ``point``: the phase at the actuator, ``H = 1``.

A layer moving along the unit vector ``(cos a, sin a)`` is synthesised in its own frame (``f_u`` along the wind,
``f_w`` across): telescope-frame frequencies are ``f_x = f_u cos a - f_w sin a``, ``f_y = f_u sin a + f_w cos a``.
"""

from __future__ import annotations

import numpy as np

from eofnn.lazy import lazy_module

torch = lazy_module("torch")

#: The sensing kernels a layer may be seen through.
KERNELS = ("subaperture", "point")


def kernel_power(kernel: str, pitch_m: float, f_u: np.ndarray, f_w: np.ndarray, cos: np.floating,
                 sin: np.floating) -> np.ndarray | None:
    """``|H|²`` at wind-frame frequencies ``(f_u, f_w)`` (cycles/m, broadcast together), or ``None`` for a kernel
    that passes every frequency unchanged (``point``)."""
    if kernel == "subaperture":
        return (np.sinc(pitch_m * (f_u * cos - f_w * sin)) * np.sinc(pitch_m * (f_u * sin + f_w * cos))) ** 2
    return None


def apply_kernel_amplitude_(amplitude: torch.Tensor, kernel: str, pitch_m: float, f_u: torch.Tensor,
                            f_w: torch.Tensor, cos: np.floating, sin: np.floating) -> torch.Tensor:
    """``amplitude *= |H|`` in place at wind-frame frequencies ``(f_u, f_w)`` (cycles/m, broadcast to
    ``amplitude``'s shape); ``amplitude`` is returned."""
    if kernel == "subaperture":
        d = pitch_m
        sincs = torch.sinc(d * (f_u * cos - f_w * sin)).mul_(torch.sinc(d * (f_u * sin + f_w * cos)))
        amplitude.mul_(sincs.abs_())
    return amplitude
