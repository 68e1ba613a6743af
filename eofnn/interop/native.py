"""eofnn's own loop physics as a simulator adapter: a scenario's turbulence on the actuator grid, its plant's DM and a
sensor, one frame at a time behind :class:`~eofnn.interop.loop.SimulatorAdapter`, so that the external-simulator
driver (:func:`~eofnn.interop.loop.run_closed_loop`) runs eofnn's sensors as it runs OOPAO's and HCIPy's.

Per frame, as :class:`~eofnn.sim.loop.kernel.Loop`'s step (the controller aside, which the driver runs): the DM
applies the command through the plant, ``eps(n) = s(n) + DM(y(n))``, and the sensor's
:class:`~eofnn.sim.loop.kernel.Measurement` reports ``wfs(n)`` with its noise drawn frame by frame from the WFS-noise
stream of the realisation's seed, as :func:`~eofnn.sim.loop.runner.run_loop` draws a zonal sensor's. The residual
RMS it reports is ``eps``'s over the actuators (``run_loop``'s ``residual_rms_nm``).
"""

from __future__ import annotations

import numpy as np
import torch

from eofnn.errors import require
from eofnn.seeding import torch_generator
from eofnn.sim.loop.kernel import ZonalSensor, loop_sensor
from eofnn.sim.loop.plant import PlantModel
from eofnn.sim.scenario import Scenario

#: Turbulence frames synthesised at a time.
BLOCK_FRAMES = 1024


class NativeLoop:
    """``scenario``'s loop as a :class:`~eofnn.interop.loop.SimulatorAdapter` (module docstring).

    Parameters
    ----------
    scenario : Scenario
        Turbulence, grid, frame rate and plant (an integer delay: the adapters' loop runs whole frames; the zonal
        scenario's turbulence: a Shack-Hartmann scenario runs in :func:`~eofnn.sim.loop.runner.run_loop`).
    sensor : LoopSensor or str, optional
        The sensor (:class:`~eofnn.sim.loop.kernel.LoopSensor`, or a registered name,
        :func:`~eofnn.sim.loop.kernel.register_sensor`); ``None``: the zonal one.
    stream : str
        The turbulence stream of each realisation's seed.
    """

    name = "eofnn"

    def __init__(self, scenario: Scenario, sensor=None, stream: str = "test") -> None:
        require(not scenario.sensor.is_shack_hartmann, "sensor.kind: shack_hartmann is invalid in NativeLoop: its "
                                                       "turbulence comes with its sensor; run it with run_loop")
        plant = scenario.plant
        require(not plant.delay_fraction, f"plant.delay_frames={plant.delay_frames!r} is invalid in NativeLoop: the "
                                          "adapters run integer delays >= 1")
        self.scenario, self.stream = scenario, stream
        if sensor is None:  # the scenario's: a registered sensor its sensor.kind names, or the zonal one
            sensor = scenario.sensor.registered
        self.sensor = loop_sensor(sensor, scenario.grid) or ZonalSensor(scenario.grid.n_actuators)
        self._sensor_name = sensor if isinstance(sensor, str) else type(self.sensor).__name__
        self.positions_m = np.asarray(scenario.grid.positions_m)
        self.delay_frames = plant.whole_delay_frames
        self.frame_rate_hz = scenario.frame_rate_hz
        self._model = PlantModel(plant, scenario.grid, frame_rate_hz=scenario.frame_rate_hz)

    @property
    def n_actuators(self) -> int:
        return self.scenario.grid.n_actuators

    def reset(self, seed: int) -> None:
        self._turbulence = self.scenario.turbulence(seed, self.stream, 1)
        self._measurement = self.sensor.measurement(self.scenario.plant)
        self._measurement.reset()
        self._generator = torch_generator(seed, "wfs-noise")
        self._frame, self._block, self._first = 0, None, 0

    def _turbulence_at(self, n: int) -> torch.Tensor:
        """``s(n)`` ``(1, K)`` nm."""
        if self._block is None or not self._first <= n < self._first + self._block.shape[1]:
            self._first = n - n % BLOCK_FRAMES
            stop = min(self._first + BLOCK_FRAMES, self.scenario.atmosphere.screen_frames)
            require(n < stop, f"frame {n} is past the turbulence's atmosphere.screen_frames={stop}: raise it")
            self._block = self._turbulence.frames(self._first, stop)
        return self._block[:, n - self._first]

    def advance(self, command_nm: np.ndarray) -> tuple[np.ndarray, float]:
        n = self._frame
        s = self._turbulence_at(n)
        y = torch.from_numpy(np.asarray(command_nm, dtype=np.float64))[None]
        dm = self._model.apply_dm(y, n)
        eps = s + dm
        m = self._measurement
        noise = (m.noise(torch.randn((1, m.noise_size), generator=self._generator, dtype=torch.float64))
                 if m.noisy else None)
        wfs = m.measure(s, eps, dm, y, noise)
        self._frame = n + 1
        return wfs[0].numpy(), float(eps.pow(2).mean().sqrt())

    def project(self, command_nm: np.ndarray) -> np.ndarray:
        """The command as it is: eofnn's sensors report the modes they cannot see themselves."""
        return command_nm

    def describe(self) -> dict:
        return {"simulator": "eofnn", "sensor": self._sensor_name, "scenario": self.scenario.to_dict(),
                "residual": "RMS of eps over the actuators"}
