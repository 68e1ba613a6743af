"""The conditions of another simulator's loop, and the one-line warning when a checkpoint dropped into it was
trained in others (:mod:`eofnn.training.conditions`).

A controller that carries ``trained_conditions`` (a checkpoint's ``info["conditions"]``:
:meth:`eofnn.interop.loop.TorchControl.from_predictor`, or ``conditions=`` of :class:`~eofnn.interop.loop.FilterControl`)
is compared, after :func:`~eofnn.interop.loop.run_closed_loop`, with the loop it ran in:

- the WFS noise (nm RMS per actuator and frame): the simulator's own when it states one (``sim.wfs_noise_nm``:
  HCIPy's white noise, or 0 for OOPAO without photon noise), else identified from the loop's own telemetry as
  :func:`eofnn.training.identify.identify_plant` does: the pseudo-open-loop reconstruction ``s_hat = wfs - g y``
  (``g`` the simulator's DM gain) has the structure function ``D(l) = D_s(l) + 2 sigma²`` at lags 1 and 2, and
  smooth turbulence an even ``D_s(l) = c l² + ...``, so ``sigma² = (4 D(1) - D(2)) / 6``. Turbulence that is not
  smooth over three frames biases it up (HCIPy's layer moves by interpolation between pixels: ``docs/findings.md``);
  hence the simulator's own number where it has one;
- the DM gain the simulator applies (``sim.dm_gain``), when it says;
- the layer's wind speed (``sim.settings["wind_speed_mps"]``), when it says.

Numpy only: the adapters' signals are numpy arrays.
"""

from __future__ import annotations

import math

import numpy as np

from eofnn.training.conditions import Conditions, warn_shift

#: Settled frames the noise identification needs (fewer: the noise is reported unknown, and no noise line is given).
MIN_NOISE_FRAMES = 50


def telemetry_noise_nm(y: np.ndarray, wfs: np.ndarray, dm_gain: float) -> float | None:
    """White WFS noise RMS (nm per actuator and frame) of ``(frames, K)`` commands ``y`` and measurements ``wfs``
    recorded in the same frames (``wfs(n)`` measures the residual with ``y(n)`` applied), for a DM that applies
    ``dm_gain`` times the command (module docstring); ``None`` when there are too few frames."""
    y, wfs = np.asarray(y, dtype=np.float64), np.asarray(wfs, dtype=np.float64)
    if len(y) < MIN_NOISE_FRAMES:
        return None
    pol = wfs - dm_gain * y
    structure = [np.mean((pol[lag:] - pol[:-lag]) ** 2, 0) for lag in (1, 2)]
    variance = float(np.mean((4 * structure[0] - structure[1]) / 6))
    return math.sqrt(variance) if variance > 0 else 0.0


def loop_conditions(sim, record, settle_frames: int = 0) -> Conditions:
    """The conditions of ``sim``'s loop as ``record`` (a :class:`~eofnn.interop.loop.LoopRecord`) saw them: the
    simulator's noise, or (unstated) the noise identified from its telemetry after ``settle_frames``; the
    simulator's DM gain and wind where it says them."""
    dm_gain = getattr(sim, "dm_gain", None)
    noise, how = getattr(sim, "wfs_noise_nm", None), "as it states"
    if noise is None:
        noise = telemetry_noise_nm(record.y[settle_frames:], record.wfs[settle_frames:],
                                   1.0 if dm_gain is None else float(dm_gain))
        how = "identified from its telemetry"
    wind = getattr(sim, "settings", {}).get("wind_speed_mps")
    return Conditions(None if noise is None else float(noise), None if dm_gain is None else float(dm_gain),
                      None if wind is None else (float(wind),), f"{sim.name}'s loop, noise {how}")


def warn_loop_shift(sim, controller, record, settle_frames: int = 0) -> list[str]:
    """One line per quantity (WFS noise, DM gain, wind) in which ``sim``'s loop differs from what ``controller``'s
    predictor was trained in (``controller.trained_conditions``: nothing when it has none), each also issued as a
    :class:`~eofnn.errors.ShiftWarning`."""
    trained = getattr(controller, "trained_conditions", None)
    if trained is None:
        return []
    name = getattr(controller, "name", None) or type(controller).__name__
    return warn_shift(trained, loop_conditions(sim, record, settle_frames), f"{name} in {sim.name}'s loop")
