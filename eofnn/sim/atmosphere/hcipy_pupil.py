"""The reference study's turbulence (model ``hcipy_pupil``): HCIPy layers on the actuator-pitch pupil grid.

Each layer is an HCIPy :class:`~hcipy.InfiniteAtmosphericLayer` on ``make_pupil_grid(n_across, diameter_m)`` (one
pixel per actuator, pixel centres on the actuator centres), advanced by setting ``layer.t = n dt`` and read at the
active actuators: what the study (Fowler et al. 2023) most likely did. HCIPy moves its screen by whole pixels,
extruding a new row or column at the rim each time, and interpolates the sub-pixel remainder, so the error of a
predictor comes in bursts where new columns enter (its open-loop EOF floor in the reference scenario:
``docs/findings.md``). Kept for faithful reproduction, not for speed: frames are generated one after another. A
frame range that does not start where the previous one ended restarts the layer from frame 0 with the same seed,
so any range is reproducible, at the cost of regenerating the frames before it.
"""

from __future__ import annotations

import math

import hcipy
import numpy as np
import torch

from eofnn.sim.atmosphere.strip import NM_PER_SCREEN_UNIT
from eofnn.sim.grid import ActuatorGrid


class HcipyPupilLayer:
    """One realisation of one layer, as HCIPy evolves it on the actuator-pitch pupil grid.

    Parameters
    ----------
    grid : ActuatorGrid
        Actuators: the HCIPy grid has ``n_across`` x ``n_across`` pixels at the actuator pitch.
    r0_m, r0_wavelength_m, outer_scale_m : float
        Layer's Fried parameter (m) at a wavelength (m), and the outer scale (m).
    wind_speed_mps, wind_direction_deg : float
        Wind speed (m/s) and direction (degrees from +x towards +y).
    frame_period_s : float
        Time between frames in seconds.
    seed : SeedSequence
        Seed of this realisation; HCIPy's layer draws from a generator seeded with it.
    """

    def __init__(self, grid: ActuatorGrid, r0_m: float, r0_wavelength_m: float, outer_scale_m: float,
                 wind_speed_mps: float, wind_direction_deg: float, frame_period_s: float,
                 seed: np.random.SeedSequence) -> None:
        self._pupil_grid = hcipy.make_pupil_grid(grid.n_across, grid.diameter_m)
        self._active = grid.mask.ravel()
        self._cn2 = hcipy.Cn_squared_from_fried_parameter(r0_m, r0_wavelength_m)
        self._outer_scale_m = outer_scale_m
        angle = math.radians(wind_direction_deg)
        self._velocity = wind_speed_mps * np.array([math.cos(angle), math.sin(angle)])
        self._frame_period_s = frame_period_s
        self._seed = seed
        self._reset()

    def _reset(self) -> None:
        self.layer = hcipy.InfiniteAtmosphericLayer(self._pupil_grid, self._cn2, self._outer_scale_m,
                                                    velocity=self._velocity, seed=np.random.default_rng(self._seed))
        self._next_frame = 0

    def _read(self) -> np.ndarray:
        return np.asarray(self.layer.phase_for(1.0))[self._active] * NM_PER_SCREEN_UNIT

    def frames(self, start: int, stop: int, basis: torch.Tensor | None = None) -> torch.Tensor:
        """OPD (nm) of frames ``start..stop-1`` at the actuators, ``(frames, n_actuators)``; ``basis`` projected out."""
        if start < self._next_frame:
            self._reset()  # HCIPy cannot go back in time: replay from frame 0
        out = np.empty((stop - start, int(self._active.sum())))
        for n in range(self._next_frame, stop):
            self.layer.t = n * self._frame_period_s
            if n >= start:
                out[n - start] = self._read()
        self._next_frame = max(stop, self._next_frame)
        result = torch.as_tensor(out)
        return result if basis is None else result - (result @ basis) @ basis.T
