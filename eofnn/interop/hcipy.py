"""An HCIPy closed loop as an eofnn simulator adapter: infinite frozen-flow layer, Gaussian-influence DM, a
phase-projection sensor.

HCIPy has no loop of its own (its AO tutorials write one: ``dm.actuators -= gain * reconstructor.dot(slopes)``);
this adapter is that loop's physics, with HCIPy's objects, imported only when an :class:`HcipyLoop` is made:

- a pupil grid (``hcipy.make_pupil_grid``) with ``pupil_pixels_per_subaperture`` pixels per actuator pitch and a
  circular aperture of ``diameter_m``;
- one ``InfiniteAtmosphericLayer`` (von Karman, ``r0_m`` at 500 nm, ``outer_scale_m``), moved on by one frame
  per step (``layer.t``), with the seed of the realisation;
- a DM of ``hcipy.make_gaussian_influence_functions`` in Fried geometry (``n_subapertures + 1`` across at the
  subaperture corners, ``crosstalk`` at the nearest neighbour), actuators within ``0.75`` pitch of the rim kept,
  applying ``dm_gain`` times the command (OPD, nm per nm);
- a phase-projection sensor: the least-squares projection of the residual OPD (piston removed) on the influence
  functions, plus white noise of ``wfs_noise_nm`` per actuator. It does not alias: aliasing is measured with
  OOPAO's Shack-Hartmann (:mod:`eofnn.interop.oopao`).

Commands are projected on the DM modes the sensor sees (piston is not: the residual is piston-free), singular
values of the influence functions below ``rcond`` of the largest dropped.
"""

from __future__ import annotations

import numpy as np

from eofnn.errors import ConfigError
from eofnn.interop.loop import check_command
from eofnn.validation import Interval, check_value

WAVELENGTH_M = 500e-9


class HcipyLoop:
    """One frame of an HCIPy AO system at a time (:class:`eofnn.interop.loop.SimulatorAdapter`).

    Parameters
    ----------
    n_subapertures : int
        Actuator pitches across the pupil (the DM has one more actuator across).
    diameter_m : float
        Telescope diameter (m).
    pupil_pixels_per_subaperture : int
        OPD pixels per actuator pitch.
    r0_m, outer_scale_m, wind_speed_mps, wind_direction_deg : float
        The layer (r0 at 500 nm).
    frame_rate_hz : float
        Loop rate (Hz).
    delay_frames : int
        Loop delay in frames.
    dm_gain : float
        What the DM applies per unit of command.
    wfs_noise_nm : float
        White measurement noise per actuator and frame (nm RMS).
    crosstalk : float
        Influence function at the nearest actuator (HCIPy's parameter).
    rcond : float
        DM modes whose singular value is below this fraction of the largest are not controlled.
    """

    name = "hcipy"

    def __init__(self, n_subapertures: int = 10, diameter_m: float = 2.0, *, pupil_pixels_per_subaperture: int = 4,
                 r0_m: float = 0.15, outer_scale_m: float = 25.0, wind_speed_mps: float = 20.0,
                 wind_direction_deg: float = 0.0, frame_rate_hz: float = 1000.0, delay_frames: int = 2,
                 dm_gain: float = 1.0, wfs_noise_nm: float = 0.0, crosstalk: float = 0.15,
                 rcond: float = 0.1) -> None:
        check_value("n_subapertures", n_subapertures, Interval(2, 200, integer=True))
        check_value("diameter_m", diameter_m, Interval(0, 100, closed="right", unit="m"))
        check_value("pupil_pixels_per_subaperture", pupil_pixels_per_subaperture, Interval(2, 32, integer=True))
        check_value("delay_frames", delay_frames, Interval(1, 100, integer=True, unit="frames"))
        check_value("dm_gain", dm_gain, Interval(0, 100, closed="right"))
        check_value("wfs_noise_nm", wfs_noise_nm, Interval(0, 1e4, unit="nm"))
        check_value("rcond", rcond, Interval(0, 1, closed="neither"))
        try:
            import hcipy
        except ImportError as err:  # a dependency of eofnn: only a broken environment lacks it
            raise ConfigError(f"the HCIPy adapter needs hcipy ({err})") from None
        self._hcipy = hcipy
        self.settings = {"n_subapertures": n_subapertures, "diameter_m": diameter_m,
                         "pupil_pixels_per_subaperture": pupil_pixels_per_subaperture, "r0_m": r0_m,
                         "outer_scale_m": outer_scale_m, "wind_speed_mps": wind_speed_mps,
                         "wind_direction_deg": wind_direction_deg, "frame_rate_hz": frame_rate_hz,
                         "delay_frames": delay_frames, "dm_gain": dm_gain, "wfs_noise_nm": wfs_noise_nm,
                         "crosstalk": crosstalk, "rcond": rcond}
        self.dm_gain, self.wfs_noise_nm = float(dm_gain), float(wfs_noise_nm)
        self.delay_frames, self.frame_rate_hz = int(delay_frames), float(frame_rate_hz)
        self._make_pupil()
        self._make_dm(crosstalk)
        self._make_sensor(rcond)

    def _make_pupil(self) -> None:
        hc, s = self._hcipy, self.settings
        n, d = s["n_subapertures"], s["diameter_m"]
        self.pupil_grid = hc.make_pupil_grid(n * s["pupil_pixels_per_subaperture"], d)
        # make_circular_aperture: HCIPy 0.7's name (circular_aperture, its older one, warns there).
        aperture = getattr(hc, "make_circular_aperture", None) or hc.circular_aperture
        self._pupil = np.asarray(aperture(d)(self.pupil_grid)) > 0.5
        self._cn2 = hc.Cn_squared_from_fried_parameter(s["r0_m"], WAVELENGTH_M)

    def _make_dm(self, crosstalk: float) -> None:
        hc, s = self._hcipy, self.settings
        n, d = s["n_subapertures"], s["diameter_m"]
        pitch = d / n
        basis = hc.make_gaussian_influence_functions(self.pupil_grid, n + 1, pitch, crosstalk=crosstalk)
        actuators = hc.make_uniform_grid([n + 1, n + 1], [(n + 1) * pitch] * 2)  # Fried: corners of subapertures
        x, y = np.asarray(actuators.x), np.asarray(actuators.y)
        valid = np.hypot(x, y) <= d / 2 + 0.75 * pitch
        self.positions_m = np.stack([x[valid], y[valid]], 1)
        matrix = basis.transformation_matrix
        matrix = matrix.toarray() if hasattr(matrix, "toarray") else np.asarray(matrix)
        self._influence = matrix[self._pupil][:, valid]  # (pupil pixels, K): OPD per unit command

    def _make_sensor(self, rcond: float) -> None:
        centred = self._influence - self._influence.mean(0)  # what the piston-free residual shows of each actuator
        u, singular, vt = np.linalg.svd(centred, full_matrices=False)
        kept = int((singular > rcond * singular[0]).sum())
        self._seen = vt[:kept].T
        self.n_seen = kept
        self._projection = (vt[:kept].T / singular[:kept]) @ u[:, :kept].T  # (K, pixels): least squares

    @property
    def n_actuators(self) -> int:
        return len(self.positions_m)

    def describe(self) -> dict:
        return {"simulator": "hcipy", **self.settings, "n_actuators": self.n_actuators, "n_seen_modes": self.n_seen,
                "pupil_pixels": int(self._pupil.sum()),
                "measurement": "wfs = least-squares projection of the residual OPD on the DM influence functions "
                               "+ white noise (no aliasing)"}

    def reset(self, seed: int) -> None:
        s = self.settings
        angle = np.deg2rad(s["wind_direction_deg"])
        velocity = s["wind_speed_mps"] * np.array([np.cos(angle), np.sin(angle)])
        self.layer = self._hcipy.InfiniteAtmosphericLayer(self.pupil_grid, self._cn2, s["outer_scale_m"], velocity,
                                                          use_interpolation=True, seed=np.random.default_rng(seed))
        self._noise = np.random.default_rng(int(seed) + 7)
        self._frame = 0

    def project(self, command_nm: np.ndarray) -> np.ndarray:
        return self._seen @ (self._seen.T @ command_nm)

    def turbulence_opd_nm(self) -> np.ndarray:
        """The current turbulence OPD over the pupil (nm)."""
        phase = np.asarray(self.layer.phase_for(WAVELENGTH_M))[self._pupil]
        return phase * WAVELENGTH_M / (2 * np.pi) * 1e9

    def advance(self, command_nm: np.ndarray) -> tuple[np.ndarray, float]:
        command = check_command(command_nm, self.n_actuators)
        self._frame += 1
        self.layer.t = self._frame / self.frame_rate_hz
        residual = self.turbulence_opd_nm() + self.dm_gain * (self._influence @ command)
        residual -= residual.mean()
        measurement = self._projection @ residual
        if self.wfs_noise_nm:
            measurement = measurement + self.wfs_noise_nm * self._noise.standard_normal(self.n_actuators)
        return measurement, float(np.sqrt(np.mean(residual ** 2)))
