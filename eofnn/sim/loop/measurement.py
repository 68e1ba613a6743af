"""The Shack-Hartmann's measurement in the loop (:class:`ShackHartmannMeasurement`, a
:class:`~eofnn.sim.loop.kernel.Measurement`): what the real-time computer reports of the residual through the slopes,
the reconstructor and the fill of the modes it cuts (:mod:`eofnn.sim.loop.sensing` says why each term is there)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eofnn.lazy import lazy_module
from eofnn.sim.loop.kernel import is_one

if TYPE_CHECKING:  # numpy, scipy and torch are imported when a Shack-Hartmann is built, not with the config
    from eofnn.sim.sensing.pupil import LoopOperators

torch = lazy_module("torch")


def scaled_slope_noise(operators: LoopOperators, unit: torch.Tensor, sigma_nm: float) -> torch.Tensor:
    """``n``: unit normal slope draws ``(..., 2 n_sub)`` times ``sigma_nm`` and each slope's
    :attr:`~eofnn.sim.sensing.shack_hartmann.ShackHartmannSensor.slope_noise_scale` (partly lit subapertures)."""
    noise = sigma_nm * unit
    scale = operators.sensor.slope_noise_scale
    return noise if (scale == 1).all() else noise * torch.as_tensor(scale, device=unit.device)


def nominal_dm(plant, dm_gain, wfs_gain) -> bool:
    """Whether the DM applies the command as sent and the sensor has unit gain: ``P DM(y) + (I - P) y`` is then ``y``
    itself (one ``K x K`` product a frame saved)."""
    return (is_one(dm_gain) and not plant.misregistration_x and not plant.misregistration_y
            and plant.nonlinearity == "none" and plant.dm_gain_drift is None and is_one(wfs_gain))


def sensed_turbulence(products: dict[str, torch.Tensor], reconstructor: torch.Tensor | None,
                      isolate: str) -> torch.Tensor | None:
    """What the computer reads of the turbulence where it is not the loop's truth ``s = R S phi``: ``R_mmse S phi``
    ``(..., K)`` through an MMSE ``reconstructor`` (``products``' ``slopes``, ``S phi``); ``None`` for least squares
    (``reconstructor`` ``None``: it reads ``s``) and for ``isolate: perfect`` (it reads the DM's fit, ``s`` too)."""
    if reconstructor is None or isolate == "perfect":
        return None
    return products["slopes"] @ reconstructor.T


class CommandsSent:
    """The commands acting over a frame, ``y_sent``, as the DM averages them for a fractional delay (``fraction``):
    what a real-time computer reports in the modes its reconstructor cuts (``(I - P) y_sent``). A measurement that
    fills those modes derives from it and sets ``fraction``."""

    fraction: float = 0.0
    _y_previous = None

    def reset(self) -> None:
        self._y_previous = None

    def sent(self, y: torch.Tensor) -> torch.Tensor:
        """``y_sent`` of this frame's command ``y`` (the last frame's kept for the next)."""
        if not self.fraction:
            return y
        previous = torch.zeros_like(y) if self._y_previous is None else self._y_previous
        sent, self._y_previous = (1 - self.fraction) * y + self.fraction * previous, y
        return sent


class ShackHartmannMeasurement(CommandsSent):
    """The real-time computer's measurement through the Shack-Hartmann (module docstring), a
    :class:`~eofnn.sim.loop.kernel.Measurement`: ``wfs = wfs_gain (R S phi + P DM) + (I - P) y_sent + R n``, ``R``
    the least-squares reconstructor or the MMSE one (then ``R S phi`` is the turbulence the loop is told it
    ``sensed``, :func:`sensed_turbulence`, and ``P = R D`` is no projector).

    Parameters
    ----------
    operators : LoopOperators
        The sensor's operators (the least-squares ``R`` and ``P``, ``D``, the slopes' noise scale).
    reconstructor : Tensor or None
        The MMSE ``R`` ``(K, 2 n_sub)`` the computer applies (``P = R D``); ``None``: the least-squares one.
    sigma_nm : float
        RMS white noise per slope (nm).
    wfs_gain : float or Tensor
        The sensor's gain (``(batch, 1)``: one per row).
    fraction : float
        The delay's fraction: the commands sent over a frame are averaged as the DM averages them.
    identity_dm : bool
        The DM applies the command as sent and the gain is 1 (:func:`nominal_dm`): ``wfs = R S phi + DM + R n``.
    """

    def __init__(self, operators: LoopOperators, reconstructor: torch.Tensor | None, sigma_nm: float, wfs_gain,
                 fraction: float, identity_dm: bool) -> None:
        projector = operators.projector if reconstructor is None else reconstructor @ operators.interaction_matrix
        self.operators, self.projector_t, self.sigma_nm = operators, projector.T.contiguous(), sigma_nm
        self.reconstructor_t = (operators.reconstructor if reconstructor is None else reconstructor).T
        self.gain, self.fraction, self.identity_dm = wfs_gain, fraction, identity_dm
        self.noise_size, self.noisy = operators.sensor.n_slopes, sigma_nm > 0

    def slope_noise(self, unit: torch.Tensor) -> torch.Tensor:
        """``n`` ``(..., 2 n_sub)`` of unit draws (:func:`scaled_slope_noise`)."""
        return scaled_slope_noise(self.operators, unit, self.sigma_nm)

    def noise(self, unit: torch.Tensor) -> torch.Tensor:
        """``R n`` ``(..., K)`` of unit slope draws ``(..., 2 n_sub)``."""
        return self.slope_noise(unit) @ self.reconstructor_t

    def measure(self, s, eps, dm, y, noise):
        """``wfs`` of ``s = R S phi`` (the sensed turbulence, ``R`` the computer's) and the DM term ``dm``; ``y``
        fills the cut modes."""
        if self.identity_dm:  # dm is the command sent (averaged like it for a fractional delay)
            wfs = s + dm
            return wfs if noise is None else wfs + noise
        wfs = s + dm @ self.projector_t
        if not is_one(self.gain):
            wfs = self.gain * wfs
        sent = self.sent(y)
        wfs = wfs + sent - sent @ self.projector_t  # the cut modes: what the computer sent there
        return wfs if noise is None else wfs + noise

    def to(self, device) -> ShackHartmannMeasurement:
        self.projector_t, self.reconstructor_t = self.projector_t.to(device), self.reconstructor_t.to(device)
        if isinstance(self.gain, torch.Tensor):
            self.gain = self.gain.to(device)
        return self
