"""The pyramid in the loop (``sensor.kind: pyramid``): the residual phase over the pupil read through the pyramid
each frame.

The pyramid (:mod:`eofnn.sim.sensing.pyramid`) is not linear in the phase, so unlike the Shack-Hartmann
(:mod:`eofnn.sim.loop.sensing`) its reading of the residual is not the reading of the turbulence plus that of the
DM: every frame the loop forms the residual phase ``phi + IF DM(y)`` on the pyramid's own pupil points (the exact
frozen-flow phase is synthesised there, ``kernel: point``, as on a Shack-Hartmann's fine grid), propagates it
through the modulated pyramid to the detector and reconstructs with the least-squares ``R`` of its push-pull
interaction matrix (:mod:`eofnn.sim.sensing.pyramid_pupil`). About a large residual the pyramid's response is smaller
than about a flat wavefront (its optical gains, :mod:`eofnn.sim.sensing.optical_gains`): the loop sees that as a
lower loop gain, as a real one does.

- the loop's truth in command space (the controllers' and predictors' ``s``) is the DM's fit of the phase on the
  modes the reconstructor keeps, ``P F phi`` (``P = R D``): the pyramid has no linear reading of the phase alone;
- the measurement is ``wfs = wfs_gain R s(phi + IF DM(y)) + (I - P) y + n``: ``s(.)`` the signals (slopes maps by
  default) with photon and read noise drawn on the detector's pixels, ``(I - P) y`` what the computer reports in the
  modes its reconstructor cuts (the command it sent, as for the Shack-Hartmann), ``n`` the plant's white
  ``wfs_noise_nm`` per actuator. Photon noise is drawn per pixel as a normal of the Poisson variance, ``N + sqrt(N +
  sigma_e²) xi`` (``N`` the pixel's expected photons, ``sigma_e`` the read noise): exact in mean and variance, from
  the loop's noise generator;
- the residual over the pupil is scored as the Shack-Hartmann's (:class:`~eofnn.sim.loop.sensing.ShackHartmannTurbulence`
  provides the chunks, here with every frame's phase kept).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

from eofnn.errors import ConfigError, require
from eofnn.lazy import lazy_module
from eofnn.sim.atmosphere.turbulence import Atmosphere
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.loop.kernel import is_one
from eofnn.sim.loop.measurement import CommandsSent
from eofnn.sim.loop.sensing import ShackHartmannTurbulence
from eofnn.sim.sensing.sensor import Sensor

if TYPE_CHECKING:  # numpy, scipy and torch are imported when a pyramid is built, not with the config
    from eofnn.sim.sensing.pyramid import Pyramid
    from eofnn.sim.sensing.pyramid_pupil import PyramidLoopOperators

torch = lazy_module("torch")

_OPERATORS: dict = {}


def pyramid_operators(grid: ActuatorGrid, config: Pyramid) -> PyramidLoopOperators:
    """The pyramid built and calibrated on ``grid`` with the operators the loop needs (kept: a study builds it once)."""
    key = (repr(grid), repr(config))
    if key not in _OPERATORS:
        if len(_OPERATORS) >= 4:
            _OPERATORS.pop(next(iter(_OPERATORS)))
        from eofnn.sim.sensing.pyramid import PyramidSensor
        from eofnn.sim.sensing.pyramid_pupil import PyramidLoopOperators

        _OPERATORS[key] = PyramidLoopOperators(PyramidSensor(grid, config))
    return _OPERATORS[key]


class PyramidMeasurement(CommandsSent):
    """The real-time computer's measurement through the pyramid (module docstring), a
    :class:`~eofnn.sim.loop.kernel.Measurement` whose ``measure`` is given the frame's turbulent phase over the pupil
    ``(batch, n_pupil)`` where the Shack-Hartmann's is given ``s``.

    Parameters
    ----------
    operators : PyramidLoopOperators
    photons : float or None
        Photons over the pupil per frame (``None``: no photon or read noise).
    read_noise_e : float
        Read noise per pixel and frame (electrons RMS).
    sigma_nm : float
        The plant's white noise per actuator (nm RMS).
    wfs_gain : float or Tensor
        The sensor's gain (``(batch, 1)``: one per row).
    fraction : float
        The delay's fraction: the commands sent over a frame are averaged as the DM averages them.
    compensation : Tensor or None
        ``C`` ``(K, K)``: the optical gains' compensation, the reconstructor becoming ``C R``
        (:mod:`eofnn.sim.loop.optical_gain_compensation`); ``None``: none.
    perfect : bool
        The error budget's perfect sensor: no pyramid, no noise, ``wfs = P F phi + P dm`` (the residual the DM can
        fit, read linearly: no aliasing, no optical gain), the cut modes as above.
    """

    def __init__(self, operators: PyramidLoopOperators, photons: float | None, read_noise_e: float, sigma_nm: float,
                 wfs_gain, fraction: float, compensation: torch.Tensor | None = None, perfect: bool = False) -> None:
        self.operators, self.photons, self.read_noise_e, self.sigma_nm = operators, photons, read_noise_e, sigma_nm
        self.gain, self.fraction, self.perfect = wfs_gain, fraction, perfect
        optics = operators.sensor.optics
        self.n_pixels = optics.detector_pixels ** 2 if photons is not None else 0
        self.noise_size = self.n_pixels + (operators.sensor.grid.n_actuators if sigma_nm > 0 else 0)
        self.noisy = self.noise_size > 0
        reconstructor = operators.reconstructor if compensation is None else compensation @ operators.reconstructor
        self.reconstructor_t = reconstructor.T.contiguous()
        self.projector_t = operators.projector.T.contiguous()

    def noise(self, unit: torch.Tensor) -> torch.Tensor:
        """The unit draws themselves: the pixels' are scaled by their photons in :meth:`measure`."""
        return unit

    def frames(self, phase: torch.Tensor, dm: torch.Tensor, unit: torch.Tensor | None) -> torch.Tensor:
        """Detector frames ``(batch, P, P)`` of the residual ``phase + IF dm``: fractions of the pupil's photons, or
        photons (with their noise, of the unit draws ``unit``) when the measurement has photon noise."""
        ops = self.operators
        frames = ops.sensor.optics.frames(phase + ops.surface(dm))
        if self.photons is None:
            return frames
        counts = frames * self.photons
        draws = unit[:, :self.n_pixels].reshape(counts.shape)
        return counts + (counts.clamp(min=0) + self.read_noise_e ** 2).sqrt() * draws

    def measure(self, phase, eps, dm, y, noise):
        """``wfs`` of the frame's turbulent ``phase`` over the pupil and the DM term ``dm``; ``y`` fills the modes
        the reconstructor cuts."""
        if self.perfect:  # the loop's truth s = eps - dm is P F phi already
            require(eps is not None, "the pyramid's perfect sensor reads the loop's residual: run it in the loop")
            wfs = eps - dm + dm @ self.projector_t
        else:
            signals = self.operators.sensor.signals.process(self.frames(phase, dm, noise))
            wfs = signals @ self.reconstructor_t
        if not is_one(self.gain):
            wfs = self.gain * wfs
        sent = self.sent(y)
        wfs = wfs + sent - sent @ self.projector_t  # the cut modes: what the computer sent there
        if self.sigma_nm > 0:
            wfs = wfs + self.sigma_nm * noise[:, self.n_pixels:]
        return wfs

    def to(self, device) -> PyramidMeasurement:
        if str(device) != "cpu":
            raise ConfigError(f"device={device!r} is invalid for the pyramid's loop: it runs on the CPU")
        return self


class PyramidTurbulence(ShackHartmannTurbulence):
    """The turbulence of a pyramid scenario: the exact phase on the pyramid's pupil points, chunked and cached as a
    Shack-Hartmann's fine-grid phase (every frame's phase kept), with ``s = P F phi``."""

    phase_every = 1
    lazy_fit = False  # its operators make the fit with the chunk: the loop reads it

    def __init__(self, atmosphere: Atmosphere, grid: ActuatorGrid, frame_rate_hz: float, seed: int, stream: str,
                 n_realisations: int, vibrations, sensor: Sensor, isolate: str = "none") -> None:
        require(isolate in ("none", "noise_free", "perfect"),
                f"isolate={isolate!r} is invalid with sensor.kind pyramid: allowed are none, noise_free, perfect")
        self.grid, self.frame_rate_hz, self.n_realisations = grid, frame_rate_hz, n_realisations
        self.atmosphere, self.sensor, self.isolate = atmosphere, sensor, isolate
        self.seed, self.vibrations = seed, vibrations
        self.operators = pyramid_operators(grid, sensor.pyramid())
        self.fine_grid = self.operators.sensor.pupil_grid
        self._args = (replace(atmosphere, kernel="point"), self.fine_grid, frame_rate_hz, seed, stream,
                      n_realisations, vibrations)
        self._fine = None
        self.mmse_noise_weight = 1.0
        self._key = repr((self._args, repr(sensor.pyramid()), repr(grid)))

    @property
    def n_fine(self) -> int:
        return self.operators.n_pupil

    def reconstructor(self, extra_nm: float) -> None:
        """The pyramid reconstructs by least squares only (:attr:`operators`)."""
        return None

    def photons(self) -> float | None:
        """Photons over the pupil per frame from the detector's guide star (``None``: no detector, or isolated)."""
        detector = self.sensor.detector
        if detector is None or self.isolate != "none":
            return None
        return self.operators.sensor.photons_per_frame(detector.magnitude, detector.throughput,
                                                       1.0 / self.frame_rate_hz)

    def phases(self, start: int, stop: int) -> torch.Tensor:
        """The phase over the pupil ``(R, frames, n_pupil)`` of frames ``start..stop-1`` (nm)."""
        step = self.chunk_frames
        parts = [self._chunk(index)["phase"][:, max(start - index * step, 0): stop - index * step]
                 for index in range(start // step, -(-stop // step))]
        return torch.cat(parts, 1)

    def compensation(self, plant):  # -> OpticalGainCompensation or None
        """The optical gains' compensation in ``plant`` (``sensor.optical_gain_compensation``; calibrated on first
        use, :mod:`eofnn.sim.loop.optical_gain_compensation`), or ``None`` without it."""
        if not self.sensor.optical_gain_compensation:
            return None
        from eofnn.sim.loop.optical_gain_compensation import calibrate

        return calibrate(self, plant)

    def loop_measurement(self, plant, calibrated_in=None) -> PyramidMeasurement:
        """The pyramid's measurement in ``plant`` (its detector's photons, the plant's white noise, gain, delay), its
        optical gains compensated as calibrated in ``calibrated_in`` (``None``: ``plant``) where the sensor asks."""
        detector = self.sensor.detector
        read = 0.0 if detector is None else detector.read_noise_e
        sigma = plant.wfs_noise_nm if self.isolate == "none" else 0.0
        perfect = self.isolate == "perfect"  # reads linearly: nothing to compensate
        compensation = None if perfect else self.compensation(plant if calibrated_in is None else calibrated_in)
        return PyramidMeasurement(self.operators, self.photons(), read, sigma, plant.wfs_gain, plant.delay_fraction,
                                  None if compensation is None else compensation.matrix, perfect)

    def loop_sensing(self, model, slopes: bool = False) -> PyramidLoopSensing:
        return PyramidLoopSensing(self, model, slopes)

    def measurement(self, plant, dm_gain=None, wfs_gain=None):
        raise ConfigError("sensor.kind pyramid is invalid for training through the loop (the rollout) and external "
                          "drivers: the pyramid reads the phase over the pupil each frame; use the batched loop")

    def open_loop(self, start: int, stop: int, plant, generator) -> tuple[torch.Tensor, torch.Tensor]:
        """``(s, s_hat)`` of frames ``start..stop-1`` with no correction: the truth and the pyramid's noisy reading of
        it with the gain divided out. Not the POL values a loop reads: about the uncorrected turbulence the optical
        gains are lower, so open-loop training data are recorded in the loop (:func:`eofnn.data.stream.open_loop_recorded`)."""
        s = self.products(start, stop)["s"]
        phase = self.phases(start, stop)
        self.release()
        m = self.loop_measurement(replace(plant, wfs_gain=1.0), plant)
        rows, frames = phase.shape[:2]
        flat_phase = phase.reshape(rows * frames, -1)
        unit = torch.randn((rows * frames, m.noise_size), generator=generator, dtype=s.dtype) if m.noisy else None
        zeros = torch.zeros(rows * frames, self.grid.n_actuators, dtype=s.dtype)
        wfs = m.measure(flat_phase, None, zeros, zeros, unit)
        return s, wfs.reshape(rows, frames, -1)


class PyramidLoopSensing:
    """The pyramid in ``run_loop`` (module docstring): a chunk's ``s`` and phase, the measurement, the pupil's
    residual per frame."""

    pupil = True
    n_slopes = 0

    def __init__(self, turbulence: PyramidTurbulence, model, slopes: bool = False) -> None:
        require(not slopes, "record 'slopes' is invalid with sensor.kind pyramid: it measures no slopes")
        self.turbulence, self.model = turbulence, model
        self._measurement = turbulence.loop_measurement(model.plant)
        self._chunk: dict = {}
        self._phase = None

    def measurement(self) -> PyramidMeasurement:
        return self._measurement

    def chunks(self, n_frames: int, chunk: int, generator):
        for first in range(0, n_frames, chunk):
            stop = min(first + chunk, n_frames)
            self._chunk = self.turbulence.products(first, stop)
            self._phase = self.turbulence.phases(first, stop)
            if stop >= n_frames:
                self.turbulence.release()
            yield first, self._chunk["s"]

    def fit(self) -> torch.Tensor:
        """``(R, frames, K)``: the chunk's ``P F phi`` (the loop's truth ``s`` itself for the pyramid)."""
        return self._chunk["fit"]

    def noise(self, i: int, s: torch.Tensor, generator) -> torch.Tensor | None:
        """Unit draws of frame ``i``: the detector's pixels, then the actuators' white noise (drawn now)."""
        m = self._measurement
        if not m.noisy:
            return None
        return torch.randn((*s.shape[:-1], m.noise_size), generator=generator, dtype=s.dtype)

    def sensed(self, i: int) -> torch.Tensor:
        """What the pyramid reads of the turbulence at frame ``i`` of the chunk: its phase over the pupil."""
        return self._phase[:, i]

    def pupil_rms(self, dm: torch.Tensor) -> torch.Tensor:
        """``(R, frames)`` piston-removed RMS over the pupil of ``phi + IF DM`` for the chunk's applied ``dm``."""
        t = dm.shape[1]
        c = self._chunk
        return self.turbulence.operators.pupil_rms(c["z"][:, :t], c["sum"][:, :t], c["sumsq"][:, :t], dm)

    def pupil_residual(self, frame: int, dm: torch.Tensor) -> torch.Tensor:
        """``(R, n_pupil)``: ``phi + IF DM`` over the pupil at ``frame`` (every one of the pyramid's points is in it)."""
        return self.turbulence.phase_at(frame) + self.turbulence.operators.surface(dm)
