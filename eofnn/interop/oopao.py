"""An OOPAO closed loop as an eofnn simulator adapter: Shack-Hartmann or pyramid (or a perfect sensor), Fried DM.

OOPAO (https://github.com/cheritie/OOPAO, ``pip install oopao``) is imported only when an :class:`OopaoLoop` is
made, so ``import eofnn`` never needs it. The system is OOPAO's own objects, built as its tutorials do:

- ``Telescope`` of ``diameter_m`` sampled with ``pupil_pixels_per_subaperture`` pixels per subaperture, a
  ``Source`` in I band of ``magnitude``, one frozen-flow ``Atmosphere`` layer (von Karman, ``r0_m`` at 500 nm);
- a ``DeformableMirror`` in Fried geometry (``n_subapertures + 1`` actuators across, at the subaperture corners;
  Gaussian influence functions of OOPAO's default coupling), whose coefficients are set to
  ``dm_gain * command`` (a DM that applies ``dm_gain`` times what the controller believes);
- a diffractive ``ShackHartmann`` (OOPAO's default pixels per subaperture, centre of gravity), photon noise
  on or off; ``sensor="geometric"``: OOPAO's geometric Shack-Hartmann (the mean phase gradient over each lenslet's
  lit pixels: aliasing without diffraction, pixels or noise); ``sensor="pyramid"``: OOPAO's diffractive modulated
  ``Pyramid`` (``modulation_lambda_over_d``, slopes maps: :mod:`eofnn.interop.oopao_pyramid`), photon noise on or
  off; or ``sensor="perfect"``: the least-squares projection of the residual OPD on the influence functions (no
  aliasing, no noise), for separating what aliasing costs.

``opd_source`` replaces OOPAO's atmosphere by another turbulence: a function of the seed that yields one OPD map
(nm, ``(resolution, resolution)`` on the telescope's pixels) per frame, which the light crosses before the DM
(:mod:`eofnn.interop.sh_compare` feeds OOPAO eofnn's exact frozen flow this way, to tell the sensors apart from the
atmospheres).

The interaction matrix is OOPAO's (``InteractionMatrix``, one push per actuator), in slopes per nm of command;
the loop's reconstructor is its truncated pseudo-inverse (singular values below ``rcond`` of the largest dropped:
piston and waffle, which a Shack-Hartmann does not see; the pyramid's too), and commands are projected on the seen
modes, as an RTC filters them. The measurement ``wfs(n) = R @ slopes(n)`` (nm on the actuators) is what the telemetry
records (``Telemetry.from_slopes(y, slopes, reconstructor=sim.reconstructor)`` forms the same from recorded slopes); the
residual OPD RMS (nm, piston removed, over the pupil) is OOPAO's ``tel.OPD``.
"""

from __future__ import annotations

import contextlib
import io

import numpy as np

from eofnn.errors import ConfigError
from eofnn.interop.loop import check_command
from eofnn.sim.sensing.least_squares import MECHANICAL_COUPLING, surface_per_command
from eofnn.validation import Interval, OneOf, check_value

SENSORS = ("shack_hartmann", "geometric", "pyramid", "perfect")
#: The sensors with a detector (photon noise) and an optical gain to measure.
DIFFRACTIVE = ("shack_hartmann", "pyramid")


def quiet():
    """OOPAO prints banners, properties and warnings: keep them off the user's terminal."""
    return contextlib.redirect_stdout(io.StringIO())


def _import_oopao():
    try:
        with quiet():
            from OOPAO.Atmosphere import Atmosphere
            from OOPAO.calibration.InteractionMatrix import InteractionMatrix
            from OOPAO.DeformableMirror import DeformableMirror
            from OOPAO.OPD_map import OPD_map
            from OOPAO.Pyramid import Pyramid
            from OOPAO.ShackHartmann import ShackHartmann
            from OOPAO.Source import Source
            from OOPAO.Telescope import Telescope
    except ImportError as err:
        raise ConfigError(f"the OOPAO adapter needs OOPAO ({err}): pip install 'eofnn[interop]'") from None
    return Atmosphere, InteractionMatrix, DeformableMirror, OPD_map, (ShackHartmann, Pyramid), Source, Telescope


class OopaoLoop:
    """One frame of an OOPAO AO system at a time (:class:`eofnn.interop.loop.SimulatorAdapter`).

    Parameters
    ----------
    n_subapertures : int
        Shack-Hartmann subapertures (the pyramid's pixels) across the pupil (the DM has one more actuator across).
    diameter_m : float
        Telescope diameter (m).
    pupil_pixels_per_subaperture : int
        Pupil sampling: OPD pixels per subaperture (also the SH's pixels per subaperture, OOPAO's default; the
        pyramid's pupil points per detector pixel).
    sensor : {"shack_hartmann", "geometric", "pyramid", "perfect"}
        OOPAO's diffractive Shack-Hartmann, its geometric one, its modulated pyramid, or the least-squares
        projection of the residual on the DM.
    modulation_lambda_over_d : float
        The pyramid's modulation radius (``lambda / D`` in I band; ``sensor="pyramid"`` only).
    photon_noise : bool
        Photon noise on the detector (flux from ``magnitude``; the diffractive SH and the pyramid only).
    magnitude : float
        Guide star I magnitude.
    r0_m, outer_scale_m, wind_speed_mps, wind_direction_deg : float
        The single frozen-flow layer (r0 at 500 nm).
    layers : sequence of (cn2_fraction, wind_speed_mps, wind_direction_deg), optional
        Several frozen-flow layers at the ground in place of the single one (fractions summing to 1); the settings'
        ``wind_speed_mps`` and ``wind_direction_deg`` are then the first layer's.
    frame_rate_hz : float
        Loop rate (Hz).
    delay_frames : int
        Loop delay in frames (2: OOPAO's ``run_cl``).
    dm_gain : float
        What the DM applies per unit of command (1: a calibrated DM).
    rcond : float
        Singular values of the interaction matrix below this fraction of the largest are not controlled.
    opd_source : callable or None
        ``opd_source(seed)`` yields the turbulence OPD (nm, ``(resolution, resolution)``) of each frame in place of
        OOPAO's atmosphere (module docstring); ``None``: OOPAO's atmosphere.
    """

    name = "oopao"

    def __init__(self, n_subapertures: int = 10, diameter_m: float = 2.0, *, pupil_pixels_per_subaperture: int = 4,
                 sensor: str = "shack_hartmann", modulation_lambda_over_d: float = 3.0, photon_noise: bool = False,
                 magnitude: float = 8.0, r0_m: float = 0.15, outer_scale_m: float = 25.0, wind_speed_mps: float = 10.0,
                 wind_direction_deg: float = 0.0, frame_rate_hz: float = 1000.0, delay_frames: int = 2,
                 dm_gain: float = 1.0, rcond: float = 0.15, opd_source=None, layers=None) -> None:
        check_value("n_subapertures", n_subapertures, Interval(2, 200, integer=True))
        check_value("diameter_m", diameter_m, Interval(0, 100, closed="right", unit="m"))
        check_value("pupil_pixels_per_subaperture", pupil_pixels_per_subaperture, Interval(2, 32, integer=True))
        check_value("sensor", sensor, OneOf(SENSORS))
        if sensor == "pyramid":
            check_value("modulation_lambda_over_d", modulation_lambda_over_d,
                        Interval(0, pupil_pixels_per_subaperture * n_subapertures / 2 - 1, unit="lambda/D (at most "
                                 "half the pupil's pixels across less one)"))
        check_value("delay_frames", delay_frames, Interval(1, 100, integer=True, unit="frames"))
        check_value("dm_gain", dm_gain, Interval(0, 100, closed="right"))
        check_value("rcond", rcond, Interval(0, 1, closed="neither"))
        if photon_noise and sensor not in DIFFRACTIVE:
            raise ConfigError(f"photon_noise=True is invalid with sensor={sensor!r}: only the diffractive "
                              "Shack-Hartmann ('shack_hartmann') and the pyramid ('pyramid') have a detector")
        if opd_source is not None and not callable(opd_source):
            raise ConfigError(f"opd_source={opd_source!r} is invalid: it must be a function of the seed that yields "
                              "OPD maps (nm), or None for OOPAO's atmosphere")
        self._opd_source, self._opd_frames, self._opd_nm = opd_source, None, None
        layers = _layers(layers, wind_speed_mps, wind_direction_deg)
        wind_speed_mps, wind_direction_deg = layers[0][1], layers[0][2]
        self.settings = {"n_subapertures": n_subapertures, "diameter_m": diameter_m,
                         "pupil_pixels_per_subaperture": pupil_pixels_per_subaperture, "sensor": sensor,
                         **({"modulation_lambda_over_d": modulation_lambda_over_d} if sensor == "pyramid" else {}),
                         "photon_noise": bool(photon_noise), "magnitude": magnitude, "r0_m": r0_m,
                         "outer_scale_m": outer_scale_m, "wind_speed_mps": wind_speed_mps,
                         "wind_direction_deg": wind_direction_deg, "frame_rate_hz": frame_rate_hz,
                         "delay_frames": delay_frames, "dm_gain": dm_gain, "rcond": rcond,
                         "layers": [list(layer) for layer in layers]}
        self.sensor, self.photon_noise, self.dm_gain = sensor, bool(photon_noise), float(dm_gain)
        self.delay_frames, self.frame_rate_hz = int(delay_frames), float(frame_rate_hz)
        self._build(*_import_oopao())
        self._calibrate(rcond)

    def _build(self, Atmosphere, InteractionMatrix, DeformableMirror, OPD_map, sensors, Source, Telescope) -> None:
        s, n = self.settings, self.settings["n_subapertures"]
        self._InteractionMatrix = InteractionMatrix
        with quiet():
            self.tel = Telescope(resolution=s["pupil_pixels_per_subaperture"] * n, diameter=s["diameter_m"],
                                 samplingTime=1.0 / s["frame_rate_hz"], centralObstruction=0.0)
            self.ngs = Source(optBand="I", magnitude=s["magnitude"])
            self.ngs * self.tel
            fractions, speeds, directions = (list(v) for v in zip(*s["layers"], strict=True))
            self.atm = Atmosphere(telescope=self.tel, r0=s["r0_m"], L0=s["outer_scale_m"], windSpeed=speeds,
                                  fractionalR0=fractions, windDirection=directions, altitude=[0.0] * len(speeds))
            self.atm.initializeAtmosphere(self.tel)
            self.dm = DeformableMirror(telescope=self.tel, nSubap=n, mechCoupling=MECHANICAL_COUPLING, print_dm_properties=False)
            if s["sensor"] == "pyramid":
                from eofnn.interop.oopao_pyramid import build_pyramid

                self.wfs = build_pyramid(sensors[1], self.tel, n, s["modulation_lambda_over_d"])
            else:
                self.wfs = sensors[0](nSubap=n, telescope=self.tel, lightRatio=0.5,
                                      is_geometric=s["sensor"] == "geometric")
            self.ngs * self.tel * self.wfs
        self._opd_map = OPD_map(np.zeros((self.tel.resolution, self.tel.resolution)))
        self.positions_m = np.asarray(self.dm.coordinates, dtype=np.float64)
        self._pupil = np.asarray(self.tel.pupil) > 0

    def _calibrate(self, rcond: float) -> None:
        """OOPAO's interaction matrix (slopes per nm), the truncated reconstructor and the seen-mode projector."""
        k = self.n_actuators
        with quiet():
            calib = self._InteractionMatrix(self.ngs, tel=self.tel, dm=self.dm, wfs=self.wfs, M2C=np.eye(k),
                                            stroke=1e-9, nMeasurements=50, noise="off")
        self.interaction_matrix = np.asarray(calib.D) * 1e-9  # slopes per nm of command
        u, singular, vt = np.linalg.svd(self.interaction_matrix, full_matrices=False)
        kept = int((singular > rcond * singular[0]).sum())
        self.reconstructor = (vt[:kept].T / singular[:kept]) @ u[:, :kept].T  # (K, S): nm per slope unit
        self._seen, self.n_seen = vt[:kept].T, kept  # the seen command modes and how many
        self.reconstructor_name = "the truncated pseudo-inverse"
        if self.sensor == "perfect":
            self._projection = self._fit_operator()[1]

    def _fit_operator(self) -> tuple[np.ndarray, np.ndarray]:
        """``(M, F)``: the influence functions over the pupil (nm of OPD per nm of command, piston removed) and the
        least-squares projection ``F`` of a piston-free OPD on the seen commands (nm of command per nm)."""
        if not hasattr(self, "_operators"):
            modes = np.asarray(self.dm.modes)[self._pupil.ravel()].astype(np.float64)  # OOPAO: peak 1 per unit coef
            modes -= modes.mean(0)
            self._operators = modes, self._seen @ (self._seen.T @ np.linalg.pinv(modes))
        return self._operators

    @property
    def n_actuators(self) -> int:
        return int(self.dm.nValidAct)

    @property
    def surface_per_command(self) -> float:
        """nm of smooth DM surface per nm of command: OOPAO's influence functions peak at 1 and overlap, eofnn's
        commands are nm of smooth surface, so one of this loop's command units is this many of eofnn's (2.99)."""
        return surface_per_command(MECHANICAL_COUPLING)

    @property
    def controlled_modes(self) -> np.ndarray:
        """``(K, n_seen)``: the orthonormal command modes the reconstructor sees (what :meth:`project` keeps)."""
        return self._seen

    @property
    def wfs_noise_nm(self) -> float | None:
        """The measurement noise per actuator and frame (nm RMS) where the sensor has a known one: 0 without photon
        noise; ``None`` with it (it depends on the flux and the reconstructor: identified from the telemetry,
        :mod:`eofnn.interop.shift`)."""
        return None if self.photon_noise else 0.0

    @property
    def n_pixels_per_subaperture(self) -> int | None:
        """The SH's detector pixels per subaperture across (``None`` for the pyramid: one pixel per subaperture)."""
        return None if self.sensor == "pyramid" else int(self.wfs.n_pix_subap)

    def describe(self) -> dict:
        kind = {"geometric": "geometric Shack-Hartmann", "pyramid": "modulated pyramid"}.get(self.sensor,
                                                                                               "Shack-Hartmann")
        measured = (f"wfs = R @ slopes: OOPAO {kind} slopes through {self.reconstructor_name} of OOPAO's "
                    f"interaction matrix ({self.n_seen} of {self.n_actuators} modes)" if self.sensor != "perfect"
                    else "wfs = least-squares projection of the residual OPD on the DM (no aliasing)")
        return {"simulator": "oopao", **self.settings, "n_actuators": self.n_actuators, "n_seen_modes": self.n_seen,
                "sh_pixels_per_subaperture": self.n_pixels_per_subaperture, "n_slopes": int(self.wfs.nSignal),
                "measurement": measured,
                "turbulence": "OOPAO atmosphere" if self._opd_source is None else "external OPD maps"}

    def reset(self, seed: int) -> None:
        with quiet():
            if self._opd_source is not None:
                if self.tel.isPaired:
                    self.tel - self.atm
                self._opd_frames = iter(self._opd_source(int(seed)))
            elif not self.tel.isPaired:
                self.tel + self.atm
            if self._opd_source is None:
                self.atm.generateNewPhaseScreen(seed=int(seed))
            self.dm.coefs = 0
        self.wfs.cam.photonNoise = self.photon_noise
        self.wfs.cam.random_state_photon_noise = np.random.RandomState(int(seed) + 7)  # OOPAO seeds by the clock

    def project(self, command_nm: np.ndarray) -> np.ndarray:
        return self._seen @ (self._seen.T @ command_nm)

    def step_turbulence(self) -> None:
        """The turbulence of the next frame, with the light restarted through it (``src ** atm * tel``)."""
        if self._opd_source is None:
            with quiet():
                self.atm.update()
            return
        opd = np.asarray(next(self._opd_frames), dtype=np.float64)
        res = self.tel.resolution
        if opd.shape != (res, res):
            raise ConfigError(f"opd_source gave a map of shape {opd.shape}: the telescope has {res} x {res} pixels")
        self._opd_nm = opd
        self._opd_map.OPD = opd * 1e-9
        self._restart_light()

    def _restart_light(self) -> None:
        """The source's light through the turbulence of the current frame and the telescope (no DM yet)."""
        with quiet():
            if self._opd_source is None:
                self.ngs ** self.atm * self.tel
            else:
                self.ngs ** self.tel * self._opd_map

    def advance(self, command_nm: np.ndarray) -> tuple[np.ndarray, float]:
        command = check_command(command_nm, self.n_actuators)
        self.step_turbulence()
        with quiet():
            self.dm.coefs = self.dm_gain * command * 1e-9
            if self.sensor == "perfect":
                self.ngs * self.tel * self.dm
            else:
                self.ngs * self.tel * self.dm * self.wfs
        opd_nm = np.asarray(self.tel.OPD)[self._pupil] * 1e9
        self._residual_nm = opd_nm
        residual = float(np.std(opd_nm))
        if self.sensor == "perfect":
            return self._projection @ (opd_nm - opd_nm.mean()), residual
        return self.reconstructor @ self.slopes(), residual

    def slopes(self) -> np.ndarray:
        """The sensor's signals of the last frame (OOPAO's ``wfs.signal``: SH slopes, pyramid slopes maps)."""
        return np.asarray(self.wfs.signal, dtype=np.float64)

    def turbulence_opd_nm(self) -> np.ndarray:
        """The current turbulence OPD over the pupil (nm), without the DM."""
        if self._opd_source is not None:
            return self._opd_nm[self._pupil]
        return np.asarray(self.atm.OPD)[self._pupil] * 1e9

    def turbulence_fit_nm(self) -> np.ndarray:
        """The simulator's truth in command space: the least-squares fit of the current turbulence (piston removed)
        by the seen DM modes, ``(K,)`` nm of command of a DM that applies what it is told (the target of an
        anti-aliasing predictor, :mod:`eofnn.interop.antialias`)."""
        opd = self.turbulence_opd_nm()
        return self._fit_operator()[1] @ (opd - opd.mean())

    def residual_opd_nm(self) -> np.ndarray:
        """The residual OPD of the last frame over the pupil's pixels (nm, in the order of ``pupil_mask``)."""
        return self._residual_nm

    @property
    def pupil_mask(self) -> np.ndarray:
        """``(resolution, resolution)`` bool: the telescope's pupil pixels (pixel pitch ``diameter_m / resolution``)."""
        return self._pupil

    def sensor_gain(self, command_nm: np.ndarray, probe_nm: np.ndarray, *, noise_free: bool = False) -> float:
        """The sensor's optical gain on the current turbulence: the response ``R @ slopes`` to a small DM
        ``probe_nm`` added to ``command_nm`` (push-pull, same frame), projected on the probe; 1 for a linear
        sensor. Telemetry only ever sees ``dm_gain`` times this (:mod:`eofnn.training.identify`). With photon
        noise on, each probe's value carries the detector's noise (unbiased, but far larger than the gain's
        spread for a probe of a few nm); ``noise_free`` reads the two frames with the detector's noise off (the
        optics' gain about this residual, as :func:`eofnn.interop.oopao_pyramid.probe_optical_gains` reads it)."""
        probe = self.project(check_command(probe_nm, self.n_actuators, "probe"))
        response = []
        camera = getattr(self.wfs, "cam", None)
        noise = None if camera is None else camera.photonNoise
        try:
            if noise_free and camera is not None:
                camera.photonNoise = False
            for sign in (1.0, -1.0):
                self._restart_light()  # ``*`` alone would add the DM to what is there
                with quiet():
                    self.dm.coefs = self.dm_gain * (command_nm + sign * probe) * 1e-9
                    self.ngs * self.tel * self.dm * self.wfs
                response.append(self.reconstructor @ self.slopes())
        finally:
            if camera is not None:
                camera.photonNoise = noise
        return float((response[0] - response[1]) @ probe / (2 * self.dm_gain * probe @ probe))


def _layers(layers, wind_speed_mps: float, wind_direction_deg: float) -> list[tuple[float, float, float]]:
    """``[(cn2_fraction, wind_speed_mps, wind_direction_deg)]``: ``layers`` checked, or the single layer."""
    if layers is None:
        return [(1.0, float(wind_speed_mps), float(wind_direction_deg))]
    out = []
    for i, layer in enumerate(layers):
        if len(layer) != 3:
            raise ConfigError(f"layers[{i}]={layer!r} is invalid: (cn2_fraction, wind_speed_mps, wind_direction_deg)")
        fraction, speed, direction = (float(v) for v in layer)
        check_value(f"layers[{i}] cn2_fraction", fraction, Interval(0, 1, closed="right"))
        check_value(f"layers[{i}] wind_speed_mps", speed, Interval(0, 200, unit="m/s"))
        out.append((fraction, speed, direction))
    if not out or abs(sum(f for f, _, _ in out) - 1) > 1e-6:
        raise ConfigError(f"layers={layers!r} is invalid: one or more layers whose cn2_fraction sum to 1")
    return out


def fitting_error(sim: OopaoLoop, n_frames: int, seed: int, every: int = 5, start: int = 0) -> dict:
    """What the DM cannot correct: the RMS (nm, piston removed) of the turbulence minus its least-squares fit by
    the seen DM modes, every ``every`` frames from frame ``start`` to ``n_frames - 1`` of the realisation ``seed``;
    ``{"median_rms_nm", "n_frames"}``."""
    modes, projection = sim._fit_operator()
    sim.reset(seed)
    values = []
    for n in range(n_frames):
        sim.step_turbulence()
        if n >= start and (n - start) % every == 0:
            opd = sim.turbulence_opd_nm()
            opd = opd - opd.mean()
            values.append(float(np.sqrt(np.mean((opd - modes @ (projection @ opd)) ** 2))))
    return {"median_rms_nm": float(np.median(values)), "n_frames": len(values)}


def measure_sensor_gain(sim: OopaoLoop, gain: float, n_frames: int, seed: int, *, dither_nm: float = 0.0,
                        probe_nm: float = 5.0, every: int = 10, settle_frames: int = 100,
                        noise_free: bool = False) -> dict:
    """The sensor's optical gain in ``sim``'s integrator loop (gain ``gain``, plus ``dither_nm`` of white
    dither as when recording telemetry, since the gain depends on the residual): every ``every`` frames after
    ``settle_frames``, a random probe of ``probe_nm`` RMS per actuator is pushed and pulled on that frame's
    residual (``noise_free``: read with the detector's noise off, :meth:`OopaoLoop.sensor_gain`; the loop itself
    keeps its noise). Returns ``{"mean", "se", "n_probes"}``: what the identified DM gain should equal, divided by
    ``sim.dm_gain`` (a perfect sensor: 1)."""
    from eofnn.interop.loop import IntegratorControl

    if sim.sensor == "perfect":
        return {"mean": 1.0, "se": 0.0, "n_probes": 0}
    control, rng = IntegratorControl(gain, dither_nm, seed + 12), np.random.default_rng(seed + 11)
    sim.reset(seed)
    control.reset(sim.n_actuators)
    pending, gains = [np.zeros(sim.n_actuators) for _ in range(sim.delay_frames)], []
    for n in range(n_frames):
        command = sim.project(control.step(pending.pop(0)))
        measurement, _ = sim.advance(command)
        pending.append(measurement)
        if n >= settle_frames and n % every == 0:
            gains.append(sim.sensor_gain(command, probe_nm * rng.standard_normal(sim.n_actuators), noise_free=noise_free))
    gains = np.asarray(gains)
    return {"mean": float(gains.mean()), "se": float(gains.std() / np.sqrt(max(len(gains), 1))),
            "n_probes": len(gains)}
