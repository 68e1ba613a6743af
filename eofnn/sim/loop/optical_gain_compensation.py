"""A pyramid's optical gains compensated per mode (``sensor.optical_gain_compensation: true``), for every controller.

About a closed loop's residual the pyramid's response to mode ``m`` is ``g_m`` times its response about a flat
wavefront (:mod:`eofnn.sim.sensing.optical_gains`): every controller sees a loop gain lowered per mode. The
compensation measures the ``g_m`` once per scenario and plant, and divides the reconstruction by them:

- **calibration**: a closed loop of its own (stream ``optical_gains``, seed 0, one realisation,
  :data:`CALIBRATION_FRAMES` frames) with a leak-free integrator of gain :data:`CALIBRATION_GAIN`, uncompensated,
  through the scenario's own plant and pyramid (noise included); the residual over the pupil at
  :data:`CALIBRATION_PROBES` frames spread over its second half; about each, the push-pull gains of the
  Karhunen-Loeve command modes (the first as many as the reconstructor keeps modes: those it sees), averaged;
- **compensation**: ``C = I + M diag(1 / g - 1) M^T`` (``M`` the orthonormal modes), the reconstructor becoming
  ``C R``: the measurement every controller reads in the loop's kernel is ``C R s(phi + IF u)``; the modes the
  reconstructor cuts are still reported by what the computer sent. A gain below :data:`MIN_GAIN` (a mode the pyramid
  barely sees about that residual) is divided as :data:`MIN_GAIN`: dividing by less would only amplify its noise.

The gains are those about the calibrating integrator's residual: a controller whose residual is much smaller or
larger has other gains (the pyramid's gains rise as the residual falls), which the compensation does not follow.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from eofnn.lazy import lazy_module

torch = lazy_module("torch")

#: The calibrating loop: frames, integrator gain, frames probed (over its second half), smallest gain divided by.
CALIBRATION_FRAMES, CALIBRATION_GAIN, CALIBRATION_PROBES, MIN_GAIN = 240, 0.5, 4, 0.1
#: The stream and seed the calibrating loop's turbulence and noise are drawn from (independent of training and test,
#: and the same whatever stream the compensated loop runs on: one calibration per scenario and plant).
CALIBRATION_STREAM, CALIBRATION_SEED = "optical_gains", 0

_CALIBRATIONS: dict = {}


class _Integrator:
    """The calibrating loop's leak-free integrator ``y(n) = y(n - 1) - gain m(n - d)``."""

    def __init__(self, gain: float) -> None:
        self.gain = gain

    def reset(self, batch: int, n_actuators: int, delay_frames, dtype) -> None:
        self._y = torch.zeros(batch, n_actuators, dtype=dtype)

    def step(self, inp) -> torch.Tensor:
        self._y = self._y - self.gain * inp.wfs
        return self._y


class OpticalGainCompensation:
    """The measured gains and the compensation they give (module docstring).

    Attributes
    ----------
    gains : ndarray
        ``(M,)`` optical gains of the first ``M`` Karhunen-Loeve command modes about the calibrating loop's residual.
    modes : ndarray
        ``(K, M)`` those orthonormal command modes.
    residual_rms_nm : float
        The mean piston-removed RMS over the pupil of the residuals the gains were measured about.
    matrix : Tensor
        ``C`` ``(K, K)``: what the reconstruction is multiplied by.
    """

    def __init__(self, gains: np.ndarray, modes: np.ndarray, residual_rms_nm: float) -> None:
        self.gains, self.modes, self.residual_rms_nm = gains, modes, residual_rms_nm
        self.matrix = torch.as_tensor(np.eye(len(modes)) + (modes * (1.0 / self.divided_by() - 1.0)) @ modes.T)

    def divided_by(self) -> np.ndarray:
        """``(M,)``: what each mode's reconstruction is divided by (its gain, at least :data:`MIN_GAIN`)."""
        return np.maximum(self.gains, MIN_GAIN)

    def summary(self) -> dict:
        """What ``metrics.json`` reports of it: the gains divided by, their mean, the residual they were measured on."""
        return {"n_modes": len(self.gains), "gains": [float(g) for g in self.gains],
                "mean_gain": float(np.mean(self.gains)), "residual_rms_nm": self.residual_rms_nm,
                "calibration": {"frames": CALIBRATION_FRAMES, "integrator_gain": CALIBRATION_GAIN,
                                "probes": CALIBRATION_PROBES, "stream": CALIBRATION_STREAM, "seed": CALIBRATION_SEED}}


def calibrate(turbulence, plant) -> OpticalGainCompensation:
    """The compensation of ``turbulence`` (a pyramid scenario's :class:`~eofnn.sim.loop.pyramid.PyramidTurbulence`)
    in ``plant``, measured on a closed loop of its own (module docstring); kept per scenario and plant."""
    from eofnn.sim.loop.runner import run_loop
    from eofnn.sim.sensing.optical_gains import OpticalGainProbe, modal_optical_gains

    sensor = replace(turbulence.sensor, optical_gain_compensation=False)
    frames = min(CALIBRATION_FRAMES, turbulence.atmosphere.screen_frames)
    key = (repr(turbulence.atmosphere), repr(turbulence.grid), turbulence.frame_rate_hz, repr(sensor),
           repr(turbulence.vibrations), repr(plant), frames)
    if key in _CALIBRATIONS:
        return _CALIBRATIONS[key]
    calibration = type(turbulence)(turbulence.atmosphere, turbulence.grid, turbulence.frame_rate_hz,
                                    CALIBRATION_SEED, CALIBRATION_STREAM, 1, turbulence.vibrations, sensor)
    pyramid = calibration.operators.sensor
    probe = OpticalGainProbe(pyramid, frames // 2, frames, n_frames=CALIBRATION_PROBES)
    result = run_loop(calibration, plant, _Integrator(CALIBRATION_GAIN), frames, noise_seed=CALIBRATION_SEED,
                      record=(), progress=False, on_chunk=probe)
    if result.diverged or not probe.residuals:
        from eofnn.errors import ConfigError

        raise ConfigError("sensor.optical_gain_compensation=True cannot be calibrated in this scenario: the "
                          f"calibrating integrator (gain {CALIBRATION_GAIN}) diverged; remove it")
    residuals = torch.cat(probe.residuals)
    n_modes = min(pyramid.kept_modes, pyramid.grid.n_actuators - 1)
    gains, modes = modal_optical_gains(pyramid, residuals, n_modes)
    gains = gains.numpy()
    centred = residuals - residuals.mean(-1, keepdim=True)
    out = OpticalGainCompensation(gains, modes, float(centred.pow(2).mean(-1).sqrt().mean()))
    if len(_CALIBRATIONS) >= 4:
        _CALIBRATIONS.pop(next(iter(_CALIBRATIONS)))
    _CALIBRATIONS[key] = out
    return out
