"""One frame of the closed loop: the step every driver runs.

A :class:`Loop` holds the plant (:class:`~eofnn.sim.loop.plant.PlantModel`), the sensor's measurement (a
:class:`Measurement`: :class:`ZonalMeasurement` here, the Shack-Hartmann's in :mod:`eofnn.sim.loop.sensing`) and the
controller (the :class:`Controller` protocol). Its :meth:`Loop.step` is frame ``n`` of the loop,
given the turbulence ``s(n)`` (the driver streams the atmosphere) and the sensor's noise of that frame:

1. the controller gets the measurement of ``eps(n - d)`` (zeros before the first) and returns ``y(n)``;
2. the DM applies it through the plant, ``DM(y(n))``; for a fractional delay ``d + f`` (:mod:`eofnn.delay`) the
   shape acting over the frame is the time average ``(1 - f) DM(y(n)) + f DM(y(n - 1))``;
3. ``eps(n) = s(n) + DM``;
4. the sensor measures it (its gain, its noise colour, whatever it reports in the modes it cannot see).

Two drivers run it: :func:`~eofnn.sim.loop.runner.run_loop` (batched, in place: the residual written into the
chunk's array, the measurements into ring buffers) and :func:`~eofnn.training.rollout.rollout` (out of place, so the
residuals carry gradients back to a predictor's weights). The same operations in the same order: the two give the
same residuals for the same turbulence, noise draws and controller.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from eofnn.errors import ConfigError
from eofnn.lazy import lazy_module
from eofnn.sim.loop.plant import Plant, PlantModel
from eofnn.sim.sensing.sensor import LOOP_SENSORS

torch = lazy_module("torch")


@dataclass
class LoopInput:
    """What a controller sees when it computes ``y(n)``.

    Attributes
    ----------
    frame : int
        The frame ``n`` the command is for.
    wfs : Tensor
        ``(batch, n_actuators)`` WFS measurement of ``eps(n - d)`` in nm (zeros before the first one), ``d`` the
        whole frames of the delay.
    turbulence : Tensor
        ``(batch, n_actuators)`` true ``s(n - d)`` in nm: only oracle baselines (the pseudo-integrator) may use it.
    """

    frame: int
    wfs: torch.Tensor
    turbulence: torch.Tensor


@runtime_checkable
class Controller(Protocol):
    """Anything a loop can be closed with."""

    def reset(self, batch: int, n_actuators: int, delay_frames: int | float, dtype: torch.dtype) -> None:
        """Clear internal state before a run (``delay_frames``: the plant's, possibly fractional)."""

    def step(self, inp: LoopInput) -> torch.Tensor:
        """Return the command ``y(n)`` in nm, ``(batch, n_actuators)``."""


def is_one(gain) -> bool:
    """Whether ``gain`` is the number 1 (a tensor of gains, one per row, never is: it is always applied)."""
    return isinstance(gain, int | float) and gain == 1.0


class Measurement(Protocol):
    """What a sensor reports of the residual, in command space (nm), frame by frame.

    Attributes
    ----------
    noise_size : int
        Values of unit normal noise the sensor draws per row and frame (actuators, slopes, ...).
    noisy : bool
        Whether it draws any (``False``: :meth:`noise` is never called).
    """

    noise_size: int
    noisy: bool

    def reset(self) -> None:
        """Forget the commands of a previous run (a fractional delay's average)."""

    def noise(self, unit: torch.Tensor) -> torch.Tensor:
        """The measurement noise in command space, ``(..., K)`` nm, of unit normal draws ``(..., noise_size)``."""

    def measure(self, s: torch.Tensor, eps: torch.Tensor, dm: torch.Tensor, y: torch.Tensor,
                noise: torch.Tensor | None) -> torch.Tensor:
        """``wfs(n)`` ``(batch, K)`` nm of the turbulence ``s``, the residual ``eps``, the DM term ``dm`` acting over the
        frame, the command ``y(n)`` and the frame's ``noise`` (from :meth:`noise`; ``None``: none)."""

    def to(self, device) -> Measurement:
        """This measurement with its operators on ``device``."""


class ZonalMeasurement:
    """The zonal sensor (``sensor.kind: subaperture``): ``wfs = wfs_gain eps + wfs_noise_nm n``, ``n`` white per
    actuator and frame.

    Parameters
    ----------
    n_actuators : int
        ``K``.
    wfs_noise_nm : float
        RMS of the noise per actuator and frame (nm).
    wfs_gain : float or Tensor
        The sensor's gain: a number, or ``(batch, 1)``, one per row.
    """

    def __init__(self, n_actuators: int, wfs_noise_nm: float, wfs_gain) -> None:
        self.noise_size, self.sigma_nm, self.gain = n_actuators, wfs_noise_nm, wfs_gain
        self.noisy = wfs_noise_nm > 0

    def reset(self) -> None:
        pass

    def noise(self, unit: torch.Tensor) -> torch.Tensor:
        return self.sigma_nm * unit

    def measure(self, s, eps, dm, y, noise):
        out = eps if is_one(self.gain) else self.gain * eps
        return out if noise is None else out + noise

    def to(self, device) -> ZonalMeasurement:
        if isinstance(self.gain, torch.Tensor):
            self.gain = self.gain.to(device)
        return self


class LoopSensor(Protocol):
    """A sensor the drivers run: it gives its :class:`Measurement` in a plant (``dm_gain``, ``wfs_gain``: in place of
    the plant's, a number or ``(batch, 1)``, as the rollout's windows carry them)."""

    def measurement(self, plant: Plant, dm_gain=None, wfs_gain=None) -> Measurement:
        """The sensor's measurement in ``plant``."""


class ZonalSensor:
    """The zonal sensor (``sensor.kind: subaperture``) on ``n_actuators`` actuators: :class:`ZonalMeasurement`."""

    def __init__(self, n_actuators: int) -> None:
        self.n_actuators = n_actuators

    def measurement(self, plant: Plant, dm_gain=None, wfs_gain=None) -> ZonalMeasurement:
        return ZonalMeasurement(self.n_actuators, plant.wfs_noise_nm, plant.wfs_gain if wfs_gain is None else wfs_gain)


#: Sensors that read the turbulence on the actuator grid, by name: ``name -> factory(grid) -> LoopSensor``
#: (:func:`register_sensor`; the one registry, :data:`eofnn.sim.sensing.sensor.LOOP_SENSORS`, which a scenario's
#: ``sensor.kind`` is checked against). A sensor with a turbulence of its own (the Shack-Hartmann's fine grid) comes
#: with its scenario's turbulence instead.
SENSORS = LOOP_SENSORS
SENSORS["subaperture"] = lambda grid: ZonalSensor(grid.n_actuators)


def register_sensor(name: str):
    """Register a class (or factory) building a :class:`LoopSensor` from an actuator grid under ``name``: every driver
    then runs it by that name (``run_loop(..., sensor=name)``, a rollout window's ``sensor``, and another simulator's
    loop through :class:`eofnn.interop.native.NativeLoop`), and a scenario's ``sensor.kind`` may name it."""
    def add(factory):
        SENSORS[name] = factory
        return factory

    return add


def loop_sensor(sensor, grid) -> LoopSensor | None:
    """``sensor`` as the drivers run it: ``None`` stays ``None`` (the scenario's own), a registered name is built on
    ``grid`` (one :class:`~eofnn.errors.ConfigError` line for another name), an object is itself."""
    if sensor is None or not isinstance(sensor, str):
        return sensor
    if sensor not in SENSORS:
        raise ConfigError(f"sensor={sensor!r} is invalid: registered sensors are {', '.join(sorted(SENSORS))}")
    return SENSORS[sensor](grid)


@dataclass
class LoopStep:
    """What one frame of the loop produced: the command ``y(n)``, the DM term acting over the frame, the residual
    ``eps(n)`` and the measurement ``wfs(n)`` (all ``(batch, K)``, nm)."""

    y: torch.Tensor
    dm: torch.Tensor
    eps: torch.Tensor
    wfs: torch.Tensor


class Loop:
    """The closed loop's frame (module docstring): plant, sensor and controller, stepped by a driver.

    Parameters
    ----------
    model : PlantModel
        The plant bound to its grid (delay, DM, misregistration, nonlinearity, drift).
    measurement : Measurement
        The sensor's measurement.
    controller : Controller
        Computes the commands.
    dm_gain : float or Tensor, optional
        A DM gain applied after ``model``'s (``(batch, 1)``: one per row); ``None``: the model's alone.
    in_place : bool
        ``True`` (the batched simulation): the measurements and turbulence the controller reads later are copied into
        ring buffers allocated once, the residual written where :meth:`step` is told. ``False`` (the differentiable
        rollout): nothing is written in place, every tensor of a frame stays in the graph.
    """

    def __init__(self, model: PlantModel, measurement: Measurement, controller: Controller, *, dm_gain=None,
                 in_place: bool = True) -> None:
        self.model, self.measurement, self.controller = model, measurement, controller
        self.dm_gain, self.in_place = dm_gain, in_place
        plant: Plant = model.plant
        self.delay, self.fraction = plant.whole_delay_frames, plant.delay_fraction

    def reset(self, batch: int, n_actuators: int, dtype: torch.dtype, device=None) -> None:
        """Clear the loop's state (and the controller's) before a run of ``batch`` rows of ``n_actuators``."""
        self.controller.reset(batch, n_actuators, self.model.plant.delay_frames, dtype)
        self.measurement.reset()
        zeros = torch.zeros(self.delay, batch, n_actuators, dtype=dtype, device=device)
        # Slot n % delay holds frame n - delay: the measurement the controller reads, and the oracle's turbulence.
        self._wfs = list(zeros.unbind(0)) if not self.in_place else zeros.unbind(0)
        self._turbulence = list(zeros.clone().unbind(0)) if not self.in_place else zeros.clone().unbind(0)
        self._dm_previous = torch.zeros(batch, n_actuators, dtype=dtype, device=device)  # DM(y(n - 1))

    def step(self, n: int, s: torch.Tensor, noise: torch.Tensor | None = None,
             out: torch.Tensor | None = None, sensed: torch.Tensor | None = None) -> LoopStep:
        """Frame ``n`` (counted from the reset) of turbulence ``s`` ``(batch, K)`` nm and sensor noise ``noise`` (the
        measurement's :meth:`~Measurement.noise` of this frame, or ``None``); ``out``: where the residual is written
        (in place only); ``sensed``: what the sensor reads of the turbulence where it is not the loop's truth ``s``
        (a Shack-Hartmann's MMSE reconstructor), else ``None``."""
        slot = n % self.delay
        y = self.controller.step(LoopInput(n, self._wfs[slot], self._turbulence[slot]))
        dm = self.model.apply_dm(y, n)
        if self.dm_gain is not None:
            dm = self.dm_gain * dm
        if self.fraction:  # the shape acting over frame n: the time average of the commands acting over it
            f = self.fraction
            dm, self._dm_previous = (1 - f) * dm + f * self._dm_previous, dm
        eps = torch.add(s, dm, out=out) if out is not None else s + dm
        wfs = self.measurement.measure(s if sensed is None else sensed, eps, dm, y, noise)
        if self.in_place:
            self._wfs[slot].copy_(wfs)
            self._turbulence[slot].copy_(s)
        else:
            self._wfs[slot], self._turbulence[slot] = wfs, s
        return LoopStep(y, dm, eps, wfs)
