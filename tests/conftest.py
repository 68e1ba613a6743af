from __future__ import annotations

import pytest

from eofnn.sim import ActuatorGrid, Atmosphere, Layer, Plant
from eofnn.sim.scenario import Scenario


@pytest.fixture
def small_scenario() -> Scenario:
    """A 2 m telescope with 10 actuators across (76 active), one fast layer: loops run in milliseconds.

    The default physics (exact frozen flow seen through each subaperture); streams up to 4096 frames.
    """
    return Scenario(
        grid=ActuatorGrid(2.0, 10),
        atmosphere=Atmosphere(r0_m=0.1, r0_wavelength_m=500e-9, outer_scale_m=20.0, layers=(Layer(1.0, 10.0, 0.0),),
                              screen_frames=4096),
        frame_rate_hz=1000.0,
        plant=Plant(delay_frames=2),
    )
