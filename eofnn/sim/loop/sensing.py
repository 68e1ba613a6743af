"""The loop's wavefront sensor: how ``run_loop`` turns turbulence and the DM into the controller's measurement.

Two sensings share one interface (:func:`loop_sensing`):

- **Zonal** (``sensor.kind: subaperture``, the default): ``s(n)`` is the turbulence at the actuators through the
  atmosphere's kernel; the measurement is ``wfs_gain eps(n) + noise`` (:meth:`PlantModel.measure`), drawn frame by
  frame exactly as before the Shack-Hartmann existed, so no committed number moves.
- **Shack-Hartmann** (``sensor.kind: shack_hartmann``, :class:`ShackHartmannTurbulence`). The exact frozen-flow
  phase ``phi(n)`` is synthesised on the sensor's fine grid (``kernel: point``: every fine point is exact, no
  interpolation). With ``S`` the slope operator, ``IF`` the DM's influence functions, ``D = S IF``, ``R`` the
  truncated least-squares reconstructor and ``P = R D`` (the projector on the command modes ``R`` keeps):

  - the turbulence in command space, the controllers' truth and the predictors' target, is what a noise-free copy
    of the sensor reconstructs, ``s = R S phi``: aliasing included, as every measurement of it. The actuator-space
    residual is ``eps = s + DM(y)`` (``DM`` the plant's: gain, misregistration, nonlinearity), and in a nominal plant
    the measurement below is ``eps`` plus noise, exactly as in the zonal loop;
  - what the sensor cannot tell, the fitting error and the aliasing, is scored over the pupil. The DM's best fit of
    the phase on the modes the sensor sees is ``P F phi`` with ``F = (IF^T W IF)^-1 IF^T W`` (``W`` the fine points in
    the pupil): ``phi - IF P F phi`` is the fitting error, ``R S phi - P F phi`` the aliasing in command space.
    Why not ``s = P F phi``: the aliasing is large in command space (high spatial frequencies of the commands, which
    the influence functions barely pass), so a predictor fitted to it from the measurements shrinks towards zero and
    loses to the integrator even without noise (measured: ``docs/findings.md``); a target without aliasing is the
    anti-aliasing prediction's (``data.target: dm_fit``), a choice of target, not of the loop's truth;
  - the measurement is the real-time computer's: ``wfs = wfs_gain R S (phi + IF DM(y)) + R n + (I - P) y =
    wfs_gain (R S phi + P DM(y)) + R n + (I - P) y``, with ``n`` white slope noise of the sensor's RMS (photon and
    read noise, :class:`~eofnn.sim.sensing.detector.Detector`, and the plant's ``wfs_noise_nm`` per slope). ``R S phi
    - s`` is the aliasing: the phase the DM cannot fit, seen by the subapertures and reconstructed onto the actuators.
    The last term is how the computer fills the modes its reconstructor cuts (waffle, piston, edge modes): it sees
    nothing of them, so it reports there the command it sent (``y``, averaged like the DM for a fractional delay).
    Every controller's pseudo-open-loop value ``wfs - y`` is then ``R S phi + R n`` in a nominal plant, exactly as a
    slope-space ``R (s - D y)`` would be, and an integrator leaks whatever it put in those modes away instead of
    letting a per-actuator filter feed it back on itself (without it an open-loop EOF diverged while its analysis,
    which assumes ``wfs - y`` is the turbulence, called it stable: ``docs/findings.md``). The DM still applies
    those commands: the pupil's residual has them;
  - the residual over the pupil is ``phi + IF DM(y)`` on the fine points inside the pupil, its RMS taken with
    piston removed (as OOPAO's ``np.std(tel.OPD[pupil])``): fitting error included.

  - with ``sensor.reconstructor: mmse`` (:mod:`eofnn.sim.sensing.mmse`) the computer applies the noise-aware
    ``R_mmse`` in place of ``R``, in the very formula above with ``P = R_mmse D``, which is no projector. The
    pseudo-open-loop value ``wfs - y`` is then ``R_mmse (S phi + n)`` in a nominal plant: the MMSE estimate of the
    open-loop phase from pseudo-open-loop slopes, the statistics its prior describes (a closed-loop residual's are
    not), and an integrator on ``wfs`` is pseudo-open-loop control (Ellerbroek & Vogel 2003),
    ``y <- y - g (R_mmse s_pol + y)``. The truth ``s`` stays the least-squares ``R S phi`` (the actuator-space scores
    of both reconstructors are against one truth); recorded slopes still satisfy ``R_mmse slopes + (I - P) y = wfs``,
    and the telemetry carries ``R_mmse``. Its noise term is one frame's; a loop that averages many frames is served
    better by a smaller one (:attr:`ShackHartmannTurbulence.mmse_noise_weight`).

  ``isolate`` (the error budget's runs) swaps parts of the sensor for perfect ones: ``noise_free`` drops ``n``;
  ``perfect`` also reads ``P F phi`` in place of ``R S phi`` (no aliasing; ``s`` is then ``P F phi`` too).

  Recorded slopes (``run_loop(record=(..., "slopes"))``) are the sensor's own, nm of OPD difference across each
  subaperture: ``slopes = wfs_gain (S phi + D DM(y)) + n`` with ``D`` in the loop's command units (``R D = P``) and
  the very draws ``n`` whose ``R n`` the measurement holds, so ``R slopes + (I - P) y = wfs`` to rounding. ``S phi`` is
  kept in the chunk only when slopes are recorded (a chunk cached without it is synthesised again), and the noise is
  drawn as always, then multiplied by ``R^T``. A loop that records no slopes gets the very same ``R n``, kept between
  loops (:func:`~eofnn.sim.loop.readings.reconstructed_noise`): the loops of a scan, or every contender's on the test
  stream, draw the same noise, and only the first draws it. Its fit ``P F phi`` is made when a metric first asks for
  it (:attr:`ShackHartmannTurbulence.lazy_fit`).

  The fine-grid phase is what costs (16 points per actuator at 4 samples per subaperture). Everything the loop
  needs of it, ``s``, ``R S phi`` and the pupil's numbers (:mod:`eofnn.sim.sensing.pupil`), is computed a chunk of
  frames at a time and kept in a bounded cache (:data:`CACHE_BYTES`), with the phase itself at every
  :data:`PHASE_EVERY`-th frame (raw contrast): a study runs the same test stream for every controller and every
  gain of a scan, and it is synthesised once. Chunks start on multiples of their size, so a cached chunk and a
  recomputed one are the same numbers. Per frame the loop costs two ``K x K`` products (``P DM(y)`` and the pupil's
  ``u.G u``).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import replace
from typing import TYPE_CHECKING

from eofnn.errors import require
from eofnn.lazy import lazy_module
from eofnn.sim.atmosphere.turbulence import Atmosphere, Turbulence
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.loop.kernel import ZonalSensor, loop_sensor
from eofnn.sim.loop.measurement import ShackHartmannMeasurement, nominal_dm, scaled_slope_noise
from eofnn.sim.loop.readings import ShackHartmannLoopSensing, ZonalLoopSensing
from eofnn.sim.sensing.sensor import Sensor

if TYPE_CHECKING:  # numpy, scipy and torch are imported when a Shack-Hartmann is built, not with the config
    from eofnn.sim.sensing.pupil import LoopOperators
    from eofnn.sim.sensing.shack_hartmann import ShackHartmann

torch = lazy_module("torch")

#: What the budget's runs may swap for perfect: nothing, the noise, or the noise and the aliasing.
ISOLATE = ("none", "noise_free", "perfect")
#: Fine-grid values one chunk holds at most while it is computed (float64): 128 MB.
_CHUNK_VALUES = 2 ** 24
#: The chunk cache's budget (bytes): least recently used chunks leave first.
CACHE_BYTES = 2 ** 30
#: The fine-grid phase is kept at frames that are multiples of this (raw contrast's default sampling).
PHASE_EVERY = 10
_CACHE: OrderedDict = OrderedDict()
_OPERATORS: dict = {}
_MMSE: dict = {}


def loop_operators(grid: ActuatorGrid, config: ShackHartmann) -> LoopOperators:
    """The sensor built on ``grid`` with the operators the loop needs (kept: a study builds it once)."""
    key = (repr(grid), repr(config))
    if key not in _OPERATORS:
        if len(_OPERATORS) >= 4:
            _OPERATORS.pop(next(iter(_OPERATORS)))
        from eofnn.sim.sensing.pupil import LoopOperators
        from eofnn.sim.sensing.shack_hartmann import ShackHartmannSensor

        _OPERATORS[key] = LoopOperators(ShackHartmannSensor(grid, config))
    return _OPERATORS[key]


def clear_cache() -> None:
    """Forget every cached chunk (tests that time a first synthesis)."""
    _CACHE.clear()


class ShackHartmannTurbulence:
    """The turbulence of a Shack-Hartmann scenario: the fine-grid phase and what the loop and its data derive from it.

    It streams like :class:`~eofnn.sim.atmosphere.turbulence.Turbulence` on the actuator grid (``frames``,
    ``chunks``: ``s = R S phi``) and adds the sensor's side (:meth:`products`, :meth:`open_loop`)."""

    #: The fine-grid phase is kept at frames that are multiples of this (a pyramid's loop keeps every frame's).
    phase_every = PHASE_EVERY
    #: The DM's fit of a chunk is made when first asked for (:meth:`products`' ``fit``): streams no metric scores
    #: against it (a gain scan's, a recording's) never make it. A pyramid's loop reads it: made with the chunk.
    lazy_fit = True

    def __init__(self, atmosphere: Atmosphere, grid: ActuatorGrid, frame_rate_hz: float, seed: int, stream: str,
                 n_realisations: int, vibrations, sensor: Sensor, isolate: str = "none") -> None:
        require(isolate in ISOLATE, f"isolate={isolate!r} is invalid: allowed are {', '.join(ISOLATE)}")
        self.grid, self.frame_rate_hz, self.n_realisations = grid, frame_rate_hz, n_realisations
        self.atmosphere, self.sensor, self.isolate = atmosphere, sensor, isolate
        self.operators = loop_operators(grid, sensor.shack_hartmann())
        self.fine_grid = self.operators.sensor.geometry.fine_grid
        self._args = (replace(atmosphere, kernel="point"), self.fine_grid, frame_rate_hz, seed, stream,
                      n_realisations, vibrations)
        self._fine: Turbulence | None = None  # built when a chunk is not cached
        # The MMSE reconstructor's noise variance over the sensor's: 1 for one frame's estimate; a loop that averages
        # its measurements over time (an integrator of gain g: about g / (2 - g)) is better served by less.
        self.mmse_noise_weight = 1.0
        self._key = repr((self._args, repr(sensor.shack_hartmann()), repr(grid)))

    @property
    def n_fine(self) -> int:
        return self.operators.sensor.geometry.n_fine

    @property
    def fine(self) -> Turbulence:
        """The fine-grid turbulence (built on first use)."""
        if self._fine is None:
            self._fine = Turbulence(*self._args)
        return self._fine

    def release(self) -> None:
        """Drop the fine-grid turbulence (its screens and a block of up to 4096 frames of fine phase, about 1 GB at 40
        across): the cached chunks stay, a later chunk builds it again."""
        self._fine = None

    def slope_noise_nm(self, extra_nm: float) -> float:
        """RMS white noise per slope (nm): the detector's and the plant's ``extra_nm``; 0 when isolated."""
        if self.isolate != "none":
            return 0.0
        geometry = self.operators.sensor.geometry
        return self.sensor.slope_noise_nm(geometry.pitch_m, 1.0 / self.frame_rate_hz, extra_nm)

    def reconstructor(self, extra_nm: float) -> torch.Tensor | None:
        """The MMSE reconstructor ``(K, 2 n_sub)`` in the loop's units for the sensor's slope noise with the plant's
        ``extra_nm`` (``sensor.reconstructor: mmse``; the nominal noise even when isolated, so the error budget's
        runs keep the reconstructor they isolate) times :attr:`mmse_noise_weight`, or ``None``: the least-squares one
        (:attr:`operators`). Cached by sensor, atmosphere and noise: a study builds it once."""
        if self.sensor.reconstructor != "mmse":
            return None
        atm, ops = self.atmosphere, self.operators
        sigma = self.sensor.slope_noise_nm(ops.sensor.geometry.pitch_m, 1.0 / self.frame_rate_hz, extra_nm)
        key = (repr(self.grid), repr(self.sensor.shack_hartmann()), atm.r0_m, atm.r0_wavelength_m, atm.outer_scale_m,
               atm.remove_ptt, sigma, self.mmse_noise_weight)
        if key not in _MMSE:
            if len(_MMSE) >= 4:
                _MMSE.pop(next(iter(_MMSE)))
            from eofnn.sim.sensing.mmse import loop_mmse_reconstructor

            _MMSE[key] = torch.as_tensor(loop_mmse_reconstructor(ops, atm, sigma * self.mmse_noise_weight ** 0.5))
        return _MMSE[key]

    @property
    def chunk_frames(self) -> int:
        """Frames per chunk (a multiple of :data:`PHASE_EVERY`) that keep one chunk's fine phase within 128 MB."""
        frames = _CHUNK_VALUES // (self.n_realisations * self.n_fine)
        return max(PHASE_EVERY, frames - frames % PHASE_EVERY)

    def _chunk(self, index: int, slopes: bool = False) -> dict:
        """The products of aligned chunk ``index`` (frames ``index * chunk_frames ...``), cached; ``slopes``: with
        ``S phi`` (a cached chunk without it is computed again, to the same numbers, and replaced)."""
        key = (self._key, index)
        if key in _CACHE and (not slopes or "slopes" in _CACHE[key]):
            _CACHE.move_to_end(key)
            return _CACHE[key]
        _CACHE.pop(key, None)
        step = self.chunk_frames
        start, stop = index * step, min((index + 1) * step, self.atmosphere.screen_frames)
        phase = self.fine.frames(start, stop)  # (R, t, n_fine)
        flat = phase.reshape(-1, phase.shape[-1]).numpy()
        shape = phase.shape[:2]
        made = self.operators.products(flat, slopes, with_fit=False) if self.lazy_fit else \
            self.operators.products(flat, slopes)
        out = {k: v.reshape(*shape, *v.shape[1:]) for k, v in made.items()}
        every = self.phase_every
        out["phase"] = phase[:, (-start) % every::every].clone()
        size = sum(v.numel() * v.element_size() for v in out.values())
        while _CACHE and sum(c["bytes"] for c in _CACHE.values()) + size > CACHE_BYTES:
            _CACHE.popitem(last=False)
        out["bytes"] = size
        _CACHE[key] = out
        return out

    def _fitted(self, chunk: dict) -> dict:
        """``chunk`` with its ``fit`` (made now if not yet, of the whole chunk's ``z`` at once, as with the chunk)."""
        if "fit" not in chunk:
            z = chunk["z"]
            chunk["fit"] = self.operators.fit(z.reshape(-1, z.shape[-1])).reshape(z.shape)
            chunk["bytes"] += chunk["fit"].numel() * chunk["fit"].element_size()
        return chunk

    def products(self, start: int, stop: int, slopes: bool = False, fit: bool = True) -> dict[str, torch.Tensor]:
        """``s, sensed, fit, z, sum, sumsq`` of frames ``start..stop-1`` (``(R, frames, ...)``), from the cached chunks;
        ``s`` is ``sensed`` (``R S phi``; ``fit = P F phi`` for ``isolate: perfect``); ``slopes`` adds ``S phi``;
        ``fit=False`` leaves ``fit`` out where ``s`` is not it (:meth:`fit_frames` gives it later)."""
        require(0 <= start <= stop <= self.atmosphere.screen_frames,
                f"frame range [{start}, {stop}) is invalid: need 0 <= start <= stop <= atmosphere.screen_frames="
                f"{self.atmosphere.screen_frames}")
        step = self.chunk_frames
        parts = []
        fit = fit or self.isolate == "perfect"
        skip = ("phase", "bytes") + (() if slopes else ("slopes",)) + (() if fit else ("fit",))
        for index in range(start // step, -(-stop // step)):
            chunk, lo = self._chunk(index, slopes), index * step
            if fit:
                self._fitted(chunk)
            parts.append({k: v[:, max(start - lo, 0): stop - lo] for k, v in chunk.items() if k not in skip})
        out = {k: torch.cat([p[k] for p in parts], 1) for k in parts[0]}
        if self.isolate == "perfect":
            out["sensed"] = out["fit"]
        out["s"] = out["sensed"]
        return out

    def fit_frames(self, start: int, stop: int) -> torch.Tensor:
        """``fit`` ``(R, frames, K)`` of frames ``start..stop-1`` (:meth:`products`)."""
        step = self.chunk_frames
        return torch.cat([self._fitted(self._chunk(index))["fit"][:, max(start - index * step, 0): stop - index * step]
                          for index in range(start // step, -(-stop // step))], 1)

    def phase_at(self, frame: int) -> torch.Tensor:
        """The fine-grid phase ``(R, n_fine)`` of ``frame``, a multiple of :data:`PHASE_EVERY`."""
        every = self.phase_every
        require(frame % every == 0, f"frame={frame} is invalid: the phase is kept at multiples of {every}")
        step = self.chunk_frames
        return self._chunk(frame // step)["phase"][:, (frame % step) // every]

    def slope_noise(self, shape: tuple[int, int], sigma_nm: float, generator) -> torch.Tensor | None:
        """``n``: ``(R, frames, 2 n_sub)`` white slope noise of RMS ``sigma_nm`` (``None`` when 0), times each slope's
        :attr:`~eofnn.sim.sensing.shack_hartmann.ShackHartmannSensor.slope_noise_scale` (partly lit subapertures)."""
        if sigma_nm <= 0:
            return None
        unit = torch.randn((*shape, self.operators.sensor.n_slopes), generator=generator, dtype=torch.float64)
        return scaled_slope_noise(self.operators, unit, sigma_nm)

    def noise(self, shape: tuple[int, int], sigma_nm: float, generator) -> torch.Tensor | None:
        """``R n`` for ``(R, frames)`` frames of white slope noise of RMS ``sigma_nm`` (``None`` when 0)."""
        n = self.slope_noise(shape, sigma_nm, generator)
        return None if n is None else n @ self.operators.reconstructor.T

    def frames(self, start: int, stop: int) -> torch.Tensor:
        """``s`` of frames ``start..stop-1``: ``(R, frames, K)`` nm."""
        return self.products(start, stop, fit=False)["s"]

    def chunks(self, n_frames: int, chunk: int = 1024, start: int = 0):
        """Yield ``(first_frame, s)`` over ``n_frames`` frames, ``chunk`` frames at a time."""
        for first in range(start, start + n_frames, chunk):
            yield first, self.frames(first, min(first + chunk, start + n_frames))

    def open_loop(self, start: int, stop: int, plant, generator) -> tuple[torch.Tensor, torch.Tensor]:
        """``(s, s_hat)`` of frames ``start..stop-1`` with no correction: the truth and the sensor's reading of it
        with the gain divided out, ``R S phi + R n / wfs_gain`` (what pseudo-open-loop data is; through the MMSE
        reconstructor ``R_mmse (S phi + n / wfs_gain)`` when the sensor has one)."""
        mmse = self.reconstructor(plant.wfs_noise_nm)
        out = self.products(start, stop, slopes=mmse is not None, fit=False)
        self.release()
        s, s_hat = out["s"], out["sensed"]
        n = self.slope_noise(tuple(s.shape[:2]), self.slope_noise_nm(plant.wfs_noise_nm), generator)
        if mmse is not None:  # the MMSE reconstruction of the open-loop slopes
            slopes = out["slopes"] if n is None else out["slopes"] + n / plant.wfs_gain
            return s, s_hat if self.isolate == "perfect" else slopes @ mmse.T
        noise = None if n is None else n @ self.operators.reconstructor.T
        return s, s_hat if noise is None else s_hat + noise / plant.wfs_gain

    def pupil_mean_square(self, pupil: dict[str, torch.Tensor], u: torch.Tensor) -> torch.Tensor:
        """``(..., frames)`` piston-removed mean square over the pupil (nm²) of ``phi + IF u``, from :meth:`products`'
        ``z, sum, sumsq`` (``pupil``) and the applied commands ``u`` ``(..., frames, K)``: what ``run_loop`` scores
        (:meth:`~eofnn.sim.sensing.pupil.LoopOperators.pupil_rms`, squared), in torch, so that it carries gradients
        to ``u`` (the differentiable rollout's loss in a Shack-Hartmann scenario)."""
        ops = self.operators
        key = (id(ops), u.device, u.dtype)
        if getattr(self, "_gram_key", None) != key:  # G and b dense, on the commands' device
            self._gram = torch.as_tensor(ops.gram.toarray(), dtype=u.dtype, device=u.device)
            self._pupil_sums = ops.pupil_sums.to(u.device, u.dtype)
            self._gram_key = key
        n = ops.n_pupil
        mean_sq = (pupil["sumsq"] + 2 * (pupil["z"] * u).sum(-1) + (u * (u @ self._gram)).sum(-1)) / n
        mean = (pupil["sum"] + u @ self._pupil_sums) / n
        return (mean_sq - mean * mean).clamp(min=0)

    def loop_sensing(self, model, slopes: bool = False) -> ShackHartmannLoopSensing:
        """How ``run_loop`` senses this turbulence in ``model`` (:class:`ShackHartmannLoopSensing`)."""
        return ShackHartmannLoopSensing(self, model, slopes)

    def measurement(self, plant, dm_gain=None, wfs_gain=None) -> ShackHartmannMeasurement:
        """The sensor's measurement in ``plant`` (:class:`ShackHartmannMeasurement`, through :meth:`reconstructor`
        when it is MMSE: run it with the frames' ``sensed`` turbulence); ``dm_gain``, ``wfs_gain``: gains in place of
        the plant's (a number, or ``(batch, 1)``, one per row), as the differentiable rollout's windows carry them."""
        dm_gain = plant.dm_gain if dm_gain is None else dm_gain
        wfs_gain = plant.wfs_gain if wfs_gain is None else wfs_gain
        return ShackHartmannMeasurement(self.operators, self.reconstructor(plant.wfs_noise_nm),
                                        self.slope_noise_nm(plant.wfs_noise_nm), wfs_gain, plant.delay_fraction,
                                        nominal_dm(plant, dm_gain, wfs_gain))


def loop_measurement(turbulence, plant, dm_gain=None, wfs_gain=None):
    """The measurement (:class:`~eofnn.sim.loop.kernel.Measurement`) of ``turbulence``'s sensor in ``plant``: the
    Shack-Hartmann's when it carries one, else the zonal sensor's; ``dm_gain``, ``wfs_gain``: in place of the plant's
    (a number, or ``(batch, 1)``, one per row)."""
    if isinstance(turbulence, ShackHartmannTurbulence):
        return turbulence.measurement(plant, dm_gain, wfs_gain)
    return (loop_sensor(getattr(turbulence, "sensor", None), turbulence.grid)  # a registered sensor (sensor.kind)
            or ZonalSensor(turbulence.grid.n_actuators)).measurement(plant, dm_gain, wfs_gain)


def loop_sensing(turbulence, model, slopes: bool = False, sensor=None):
    """The sensing ``run_loop`` uses for ``turbulence`` (a Shack-Hartmann's when it carries one); ``slopes``: record
    the Shack-Hartmann's slopes (one :class:`ConfigError` line for the zonal sensor, which has none); ``sensor``: a
    :class:`~eofnn.sim.loop.kernel.LoopSensor` (or a registered name, :func:`~eofnn.sim.loop.kernel.register_sensor`)
    that measures a turbulence on the actuator grid in place of the scenario's (the zonal or its registered one)."""
    if isinstance(turbulence, ShackHartmannTurbulence):
        require(sensor is None, "sensor is invalid with a Shack-Hartmann scenario: its turbulence comes with its sensor")
        return turbulence.loop_sensing(model, slopes)
    require(not slopes, "record 'slopes' is invalid in this scenario: the zonal sensor (sensor.kind: subaperture) "
            "measures no slopes; record them with sensor.kind: shack_hartmann")
    sensor = getattr(turbulence, "sensor", None) if sensor is None else sensor  # None: the scenario's sensor.kind
    return ZonalLoopSensing(turbulence, model, loop_sensor(sensor, turbulence.grid))
