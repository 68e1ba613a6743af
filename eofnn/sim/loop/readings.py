"""How ``run_loop`` reads each chunk of frames: the zonal sensing and the Shack-Hartmann's (the physics of both:
:mod:`eofnn.sim.loop.sensing`, which builds them through :func:`~eofnn.sim.loop.sensing.loop_sensing`)."""

from __future__ import annotations

from collections import OrderedDict

from eofnn.errors import require
from eofnn.lazy import lazy_module
from eofnn.sim.atmosphere.turbulence import Turbulence
from eofnn.sim.loop.kernel import ZonalMeasurement
from eofnn.sim.loop.measurement import ShackHartmannMeasurement, nominal_dm, sensed_turbulence

torch = lazy_module("torch")

__all__ = ["ShackHartmannLoopSensing", "ZonalLoopSensing"]

#: The budget (bytes) of the reconstructed slope noise kept between loops (:func:`reconstructed_noise`).
NOISE_CACHE_BYTES = 2 ** 28
#: Generator state before a chunk's draws, shape, RMS and operators -> that chunk's ``R n`` and the state after.
_NOISE: OrderedDict = OrderedDict()
#: How many chunks of noise were drawn and how many were found (what tests count).
NOISE_STATS = {"drawn": 0, "reused": 0}


def clear_noise_cache() -> None:
    """Forget the kept noise (and its counts)."""
    _NOISE.clear()
    NOISE_STATS.update(drawn=0, reused=0)


def reconstructed_noise(turbulence, shape: tuple[int, int], sigma_nm: float, reconstructor: torch.Tensor,
                        generator) -> torch.Tensor | None:
    """``R n`` of a chunk of ``shape`` ``(R, frames)``: the white slope noise ``turbulence.slope_noise`` draws from
    ``generator`` (``None`` when ``sigma_nm`` is 0), times ``reconstructor.T``.

    Every loop on a stream draws its noise from a generator seeded alike (``run_loop``'s ``noise_seed``): a scan's
    loops, or every contender's on the test stream, draw the very same numbers. They are kept (least recently used
    leave first, :data:`NOISE_CACHE_BYTES` in all) by the generator's state before the draw, the shape, the RMS and
    the operators; a loop that finds them sets the generator to the state the draw left, so what it draws next is
    what it would have drawn. The same draws times the same matrix: the same numbers, bit for bit."""
    if sigma_nm <= 0:
        return None
    ops = turbulence.operators
    key = (generator.get_state().numpy().tobytes(), tuple(shape), float(sigma_nm), id(ops), id(reconstructor))
    entry = _NOISE.get(key) if NOISE_CACHE_BYTES > 0 else None  # a budget of 0: nothing kept, nothing found
    if entry is not None and entry["operators"] is ops and entry["reconstructor"] is reconstructor:
        _NOISE.move_to_end(key)
        generator.set_state(entry["after"])
        NOISE_STATS["reused"] += 1
        return entry["noise"]
    noise = turbulence.slope_noise(tuple(shape), sigma_nm, generator) @ reconstructor.T
    NOISE_STATS["drawn"] += 1
    size = noise.numel() * noise.element_size()
    if size <= NOISE_CACHE_BYTES:
        while _NOISE and sum(e["bytes"] for e in _NOISE.values()) + size > NOISE_CACHE_BYTES:
            _NOISE.popitem(last=False)
        # The operators and reconstructor are held, so their ids name them while the entry lives.
        _NOISE[key] = {"noise": noise, "after": generator.get_state(), "operators": ops,
                       "reconstructor": reconstructor, "bytes": size}
    return noise


class ZonalLoopSensing:
    """Today's sensing: ``s`` at the actuators, measured as ``wfs_gain eps + noise``, the noise drawn frame by frame;
    or, through ``sensor`` (a :class:`~eofnn.sim.loop.kernel.LoopSensor`), by another sensor of that turbulence."""

    pupil = False
    n_slopes = 0

    def __init__(self, turbulence: Turbulence, model, sensor=None) -> None:
        self.turbulence, self.model = turbulence, model
        plant = model.plant
        self._measurement = (ZonalMeasurement(turbulence.grid.n_actuators, plant.wfs_noise_nm, plant.wfs_gain)
                             if sensor is None else sensor.measurement(plant))

    def chunks(self, n_frames: int, chunk: int, generator):
        return self.turbulence.chunks(n_frames, chunk)

    def measurement(self) -> ZonalMeasurement:
        return self._measurement

    def noise(self, i: int, s: torch.Tensor, generator) -> torch.Tensor | None:
        """The noise of frame ``i`` of the chunk (``s`` its turbulence), drawn now."""
        m = self._measurement
        if not m.noisy:
            return None
        return m.noise(torch.randn((*s.shape[:-1], m.noise_size), generator=generator, dtype=s.dtype))

    def sensed(self, i: int) -> None:
        """The zonal sensor reads the loop's truth ``s`` itself."""
        return None


class ShackHartmannLoopSensing:
    """The Shack-Hartmann in the loop (:mod:`eofnn.sim.loop.sensing`): a chunk's ``s``, sensed turbulence and noise at once, the
    measurement, the pupil's residual per frame."""

    pupil = True

    def __init__(self, turbulence, model, slopes: bool = False) -> None:  # a ShackHartmannTurbulence
        require(not slopes or turbulence.isolate != "perfect",
                "record 'slopes' is invalid with isolate='perfect': that sensor reads the DM's fit, not slopes")
        self.turbulence, self.model, self.record_slopes = turbulence, model, slopes
        plant = model.plant
        self.gain = plant.wfs_gain
        self.sigma_nm = turbulence.slope_noise_nm(plant.wfs_noise_nm)
        ops = turbulence.operators
        self.n_slopes = ops.sensor.n_slopes
        # The reconstructor the computer applies: least squares, or MMSE (then P = R D is no projector).
        self.mmse = turbulence.reconstructor(model.plant.wfs_noise_nm)
        self.reconstructor = ops.reconstructor if self.mmse is None else self.mmse
        self.interaction_t = ops.interaction_matrix.T.contiguous() if slopes else None
        self.fraction = plant.delay_fraction
        # A DM that applies the command as sent: P DM(y) + (I - P) y is y itself (one K x K product a frame saved).
        self.identity_dm = nominal_dm(plant, plant.dm_gain, self.gain)
        self._chunk: dict = {}
        self._noise = self._slope_noise = self._sensed = None

    def measurement(self) -> ShackHartmannMeasurement:
        return ShackHartmannMeasurement(self.turbulence.operators, self.mmse, self.sigma_nm, self.gain,
                                        self.fraction, self.identity_dm)

    def chunks(self, n_frames: int, chunk: int, generator):
        mmse = self.mmse is not None
        for first in range(0, n_frames, chunk):
            self._range = (first, min(first + chunk, n_frames))
            out = self.turbulence.products(*self._range, self.record_slopes or mmse, fit=False)
            self._sensed = sensed_turbulence(out, self.mmse, self.turbulence.isolate)  # s stays the truth
            self._chunk = out
            shape = tuple(out["s"].shape[:2])
            if self.record_slopes:  # R n from the very draws recorded slopes hold: the same draws, and numbers
                n = self.turbulence.slope_noise(shape, self.sigma_nm, generator)
                self._slope_noise = n
                self._noise = None if n is None else n @ self.reconstructor.T
            else:  # the same draws as another loop's on this stream: kept, not drawn again
                self._noise = reconstructed_noise(self.turbulence, shape, self.sigma_nm, self.reconstructor, generator)
            if first + chunk >= n_frames:
                self.turbulence.release()
            yield first, out["s"]

    def fit(self) -> torch.Tensor:
        """``(R, frames, K)``: the chunk's ``P F phi``, the DM's least-squares fit of the true phase on the modes the
        sensor sees (no aliasing; ``s`` itself for ``isolate: perfect``), made when first asked for."""
        if "fit" not in self._chunk:
            self._chunk["fit"] = self.turbulence.fit_frames(*self._range)
        return self._chunk["fit"]

    def noise(self, i: int, s: torch.Tensor, generator) -> torch.Tensor | None:
        """``R n`` of frame ``i`` of the chunk (drawn with the chunk)."""
        return None if self._noise is None else self._noise[:, i]

    def sensed(self, i: int) -> torch.Tensor | None:
        """What the computer reads of the turbulence at frame ``i`` of the chunk where it is not the loop's truth:
        ``R_mmse S phi`` through the MMSE reconstructor (``s`` stays ``R S phi``); ``None`` otherwise."""
        return None if self._sensed is None else self._sensed[:, i]

    def slopes(self, i: int, dm: torch.Tensor) -> torch.Tensor:
        """``(R, 2 n_sub)``: the sensor's slopes of frame ``i`` of the chunk, ``wfs_gain (S phi + D dm) + n`` (nm of OPD
        difference across each subaperture; ``dm`` the DM term :meth:`measure` got)."""
        slopes = self._chunk["slopes"][:, i] + dm @ self.interaction_t
        if self.gain != 1.0:
            slopes = self.gain * slopes
        return slopes if self._slope_noise is None else slopes + self._slope_noise[:, i]

    def space(self) -> tuple[dict[str, torch.Tensor], dict]:
        """What telemetry with slopes carries beside them: the ``interaction_matrix`` ``D`` ``(2 n_sub, K)`` and the
        ``reconstructor`` ``R`` ``(K, 2 n_sub)`` in the loop's units, and a note saying which sensor made them."""
        ops = self.turbulence.operators
        sensor, geometry = ops.sensor, ops.sensor.geometry
        note = {**self.turbulence.sensor.to_dict(), "subapertures_across": geometry.subapertures_across,
                "subapertures": geometry.n_subapertures, "kept_modes": sensor.kept_modes,
                "relative_cut": sensor.relative_cut, "slope_noise_nm": self.sigma_nm,
                "slopes": "nm of OPD difference across each subaperture, x slopes then y slopes: "
                          "wfs_gain (S phi + D DM(y)) + noise",
                "measurement": "wfs = reconstructor @ slopes + (I - P) y, P = reconstructor @ interaction_matrix "
                               "(the cut modes report the command sent)"}
        return {"interaction_matrix": ops.interaction_matrix, "reconstructor": self.reconstructor}, note

    def pupil_rms(self, dm: torch.Tensor) -> torch.Tensor:
        """``(R, frames)`` piston-removed RMS over the pupil of ``phi + IF DM`` for the chunk's applied ``dm``."""
        t = dm.shape[1]
        c = self._chunk
        return self.turbulence.operators.pupil_rms(c["z"][:, :t], c["sum"][:, :t], c["sumsq"][:, :t], dm)

    def pupil_residual(self, frame: int, dm: torch.Tensor) -> torch.Tensor:
        """``(R, n_pupil)``: ``phi + IF DM`` over the pupil at ``frame`` (a multiple of
        :data:`~eofnn.sim.loop.sensing.PHASE_EVERY`)."""
        ops = self.turbulence.operators
        return (self.turbulence.phase_at(frame) + ops.surface(dm))[:, ops.pupil]
