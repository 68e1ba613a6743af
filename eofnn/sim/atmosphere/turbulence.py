"""Frozen-flow turbulence on the actuator grid: the atmosphere's description and the stream ``s(n)`` of frames.

Three models build a layer (``Atmosphere.model``):

- ``exact`` (:mod:`eofnn.sim.atmosphere.exact`, :mod:`eofnn.sim.atmosphere.anywind`): a von Kármán screen synthesised
  in the Fourier domain and evaluated at every actuator's exact position, frame ``n`` at ``x - n v dt``, seen through
  the sensing kernel (``subaperture``: the mean over each actuator's subaperture; ``point``), for any wind direction
  (lattice directions by lines of actuators, others by a non-uniform FFT across the wind). No interpolation: the
  physics to judge predictors with.
- ``hcipy_pupil`` (:mod:`eofnn.sim.atmosphere.hcipy_pupil`): HCIPy's ``InfiniteAtmosphericLayer`` on the
  actuator-pitch pupil grid advanced with ``layer.t``, as the reference study did (its rim extrusion and sub-pixel
  interpolation kept).
- ``strip`` (:mod:`eofnn.sim.atmosphere.strip`): a strip at the actuator pitch translated with B-splines. Fast, any wind
  direction, right spatial statistics; but every series is piecewise polynomial (comb peaks at multiples of
  ``v / pitch`` in temporal PSDs), which makes prediction look almost perfect.

Layers add (Cn² fractions set each layer's r0); piston, tip and tilt are removed unless asked otherwise.
Telescope vibrations (added after that removal) and boiling layers are in :mod:`eofnn.sim.atmosphere.disturbances`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from eofnn.errors import require
from eofnn.lazy import lazy_module
from eofnn.seeding import stream_seed, sub_seed
from eofnn.sim.atmosphere.anywind import build_screens, frozen_flow_layer
from eofnn.sim.atmosphere.changes import AtmosphereChange, build_changes, layer_winds, with_changes
from eofnn.sim.atmosphere.disturbances import BoilingLayer, Vibration, VibrationSeries
from eofnn.sim.atmosphere.exact import lattice_direction, project_out
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.sensing.kernels import KERNELS
from eofnn.validation import COUNT, POSITIVE, Constraint, Interval, IsBool, OneOf, OrNone, check_value, from_mapping, validated

torch = lazy_module("torch")

MODELS = ("exact", "hcipy_pupil", "strip")


@dataclass(frozen=True)
@validated
class Layer:
    """One frozen-flow layer.

    Parameters
    ----------
    cn2_fraction : float
        Fraction of the total Cn² in this layer (fractions are normalised to sum to one).
    wind_speed_mps : float
        Wind speed in m/s.
    wind_direction_deg : float
        Direction the screen moves towards, in degrees from +x towards +y.
    boiling_time_s : float or None
        E-folding time (s) of the screen's own decorrelation (model ``exact`` only; ``None`` or 0: frozen flow).
        A stress test: the layer's variance and structure function are unchanged and its temporal covariance is
        frozen flow's times ``exp(-|t| / boiling_time_s)`` (construction: :mod:`eofnn.sim.atmosphere.disturbances`).
    """

    cn2_fraction: float = 1.0
    wind_speed_mps: float = 5.1
    wind_direction_deg: float = 0.0
    boiling_time_s: float | None = None

    _constraints: ClassVar[dict[str, Constraint]] = {
        "cn2_fraction": POSITIVE,
        "wind_speed_mps": Interval(0, 1000, unit="m/s"),
        "wind_direction_deg": Interval(-360, 360, unit="degrees"),
        "boiling_time_s": OrNone(Interval(0, None, unit="s")),
    }


@dataclass(frozen=True)
@validated
class Atmosphere:
    """Turbulence profile.

    Parameters
    ----------
    r0_m : float
        Fried parameter in metres, at ``r0_wavelength_m``.
    r0_wavelength_m : float
        Wavelength at which ``r0_m`` is given, in metres.
    outer_scale_m : float
        Von Kármán outer scale L0 in metres (``inf`` for Kolmogorov; the AR extrusion is poor for large L0).
    layers : list of Layer
        Frozen-flow layers.
    oversampling : int
        Strip samples per actuator pitch; 1 samples the screen at the actuator pitch, as the reference study does.
    interpolation_order : int
        B-spline order of the sub-pixel translation: 1 (linear), 3 (cubic) or 5 (quintic, as HCIPy).
    remove_ptt : bool
        Project piston, tip and tilt out of every frame.
    model : {"exact", "hcipy_pupil", "strip"}
        How layers are built: ``exact`` (default: a von Karman screen evaluated exactly at every actuator),
        ``hcipy_pupil`` (HCIPy's layer on the actuator-pitch pupil, the study's) or ``strip`` (an HCIPy strip
        translated with B-splines; ``oversampling`` and ``interpolation_order`` are its).
    kernel : {"subaperture", "point"} or None
        Sensing kernel: ``subaperture`` (model ``exact`` only) averages the phase over each actuator's pitch x pitch
        subaperture, a perfect zonal Shack-Hartmann-like measurement; ``point`` samples the field at the actuators.
        ``None`` (the default) takes the model's own (:attr:`sensing_kernel`): ``subaperture`` for ``exact``,
        ``point`` for the others.
    screen_frames : int
        Frames one realisation of the ``exact`` model holds (frames ``0 .. screen_frames - 1``); memory and set-up
        time grow with it.
    changes : list of AtmosphereChange
        Layers' wind or strength changing at given times (:mod:`eofnn.sim.atmosphere.changes`), e.g.
        ``[{at_s: 5.0, layer: 0, wind_speed_mps: 20.0, ramp_s: 0.1}]``; none by default (stationary).
    """

    r0_m: float = 0.083
    r0_wavelength_m: float = 658e-9
    outer_scale_m: float = 20.0
    layers: list[Layer] = field(default_factory=lambda: [Layer()])
    oversampling: int = 1
    interpolation_order: int = 5
    remove_ptt: bool = True
    model: str = "exact"
    kernel: str | None = None
    screen_frames: int = 10000
    changes: list[AtmosphereChange] = field(default_factory=list)

    _constraints: ClassVar[dict[str, Constraint]] = {
        "model": OneOf(MODELS),
        "kernel": OrNone(OneOf(KERNELS)),
        "screen_frames": COUNT,
        "r0_m": Interval(0, 100, closed="right", unit="m"),
        "r0_wavelength_m": Interval(0, 1e-3, closed="right", unit="m"),
        "outer_scale_m": Interval(0, 1e4, closed="right", unit="m"),
        "oversampling": Interval(1, 16, integer=True),
        "interpolation_order": OneOf((1, 3, 5)),
        "remove_ptt": IsBool(),
    }

    def __post_init__(self) -> None:
        require(isinstance(self.layers, (tuple, list)) and len(self.layers) >= 1,
                f"layers={self.layers!r} is invalid: give a list of at least one layer")
        # A list, not a tuple: jsonargparse serialises a list of dataclasses in a resolved config, not a tuple.
        layers = [from_mapping(Layer, lay, "layer") if isinstance(lay, dict) else lay for lay in self.layers]
        require(all(isinstance(lay, Layer) for lay in layers), f"layers={self.layers!r} is invalid: each must be a layer")
        object.__setattr__(self, "layers", layers)
        object.__setattr__(self, "changes", build_changes(self.changes, layers))
        require(self.model == "exact" or self.kernel in (None, "point"),
                f"kernel={self.kernel!r} is invalid for model {self.model!r}: it samples points on the actuator-pitch "
                "grid; use kernel 'point' or model 'exact'")
        for lay in layers:
            require(not lay.boiling_time_s or self.model == "exact",
                    f"boiling_time_s={lay.boiling_time_s!r} is invalid for model {self.model!r}: boiling layers need "
                    "model 'exact'")
        if self.model == "exact":
            require(math.isfinite(self.outer_scale_m),
                    f"outer_scale_m={self.outer_scale_m!r} is invalid for model 'exact': it must be finite (metres)")
            changed = [w for i, base in enumerate(layers)
                       for w in layer_winds(base, [c for c in self.changes if c.layer == i])]
            for lay in layers + changed:
                require(lay.wind_speed_mps > 0,
                        f"wind_speed_mps={lay.wind_speed_mps!r} is invalid for model 'exact': it must be > 0 (m/s)")

    @property
    def sensing_kernel(self) -> str:
        """The kernel in use: ``kernel``, or the model's own when it is ``None``."""
        if self.kernel is not None:
            return self.kernel
        return "subaperture" if self.model == "exact" else "point"

    def layer_r0_m(self, layer: Layer) -> float:
        """Fried parameter of one layer at ``r0_wavelength_m`` (r0 scales as Cn² to the -3/5)."""
        total = sum(lay.cn2_fraction for lay in self.layers)
        return self.r0_m * (layer.cn2_fraction / total) ** (-3 / 5)


class Turbulence:
    """Streams ``s(n)``: frozen-flow turbulence in nm on the active actuators, piston/tip/tilt removed.

    Parameters
    ----------
    atmosphere : Atmosphere
        Turbulence profile.
    grid : ActuatorGrid
        Where the turbulence is sampled.
    frame_rate_hz : float
        Frames per second.
    seed : int
        Master seed.
    stream : str
        Name of the stream (``"train"``, ``"validation"``, ``"test"``, ...): streams never share a realisation.
    n_realisations : int
        Independent realisations generated side by side (the batch dimension).
    vibrations : sequence of Vibration
        Telescope vibrations added to every frame after the piston/tip/tilt projection (so they are always seen),
        drawn from the stream ``"vibration:" + stream`` (see :mod:`eofnn.sim.atmosphere.disturbances`).
    """

    def __init__(
        self,
        atmosphere: Atmosphere,
        grid: ActuatorGrid,
        frame_rate_hz: float,
        seed: int,
        stream: str = "test",
        n_realisations: int = 1,
        vibrations: Sequence[Vibration] = (),
        sensor: str | None = None,
    ) -> None:
        check_value("frame_rate_hz", frame_rate_hz, POSITIVE)
        check_value("n_realisations", n_realisations, COUNT)
        self.atmosphere = atmosphere
        self.grid = grid
        self.n_realisations = n_realisations
        self.frame_rate_hz = frame_rate_hz
        #: The registered sensor (by name) that the loop measures this turbulence with; ``None``: the zonal sensor.
        self.sensor = sensor

        prebuilt = _screens_side_by_side(atmosphere, grid, 1.0 / frame_rate_hz, seed, stream, n_realisations)

        def layer(r: int, i: int, lay: Layer, *key: int):  # a changed wind is a new screen, seeded by its index
            if not key and (r, i) in prebuilt:
                return prebuilt[r, i]
            return _layer_generator(atmosphere, grid, lay, 1.0 / frame_rate_hz, stream_seed(seed, stream, r, i, *key))

        self._strips = [
            [with_changes(layer(r, i, lay), lay, i, atmosphere.changes, frame_rate_hz,
                          lambda new, k, r=r, i=i: layer(r, i, new, k))
             for i, lay in enumerate(atmosphere.layers)]
            for r in range(n_realisations)
        ]
        self._ptt = torch.as_tensor(grid.ptt_basis())
        self._vibrations = [VibrationSeries(vibrations, grid, 1.0 / frame_rate_hz,
                                            stream_seed(seed, f"vibration:{stream}", r))
                            for r in range(n_realisations)] if vibrations else []

    def frames(self, start: int, stop: int) -> torch.Tensor:
        """OPD in nm of frames ``start..stop-1``: a ``(n_realisations, frames, n_actuators)`` float64 tensor."""
        require(0 <= start <= stop, f"frame range [{start}, {stop}) is invalid: need 0 <= start <= stop")
        basis = self._ptt if self.atmosphere.remove_ptt else None
        out = torch.empty(self.n_realisations, stop - start, self.grid.n_actuators, dtype=torch.float64)
        for r, strips in enumerate(self._strips):  # layers add in place: large fresh tensors are slow to fault in
            if self.atmosphere.model == "exact":
                for i, layer in enumerate(strips):
                    layer.write_frames(start, stop, out[r], add=i > 0)
                if basis is not None:
                    project_out(out[r], basis)
                continue
            out[r] = strips[0].frames(start, stop, basis)
            for strip in strips[1:]:
                out[r] += strip.frames(start, stop, basis)
        for r, vibrations in enumerate(self._vibrations):  # after the projection: the telescope's tip is seen
            vibrations.add_to(out[r], start, stop)
        return out

    def chunks(self, n_frames: int, chunk: int = 1024, start: int = 0):
        """Yield ``(first_frame, frames)`` over ``n_frames`` frames, ``chunk`` frames at a time."""
        for first in range(start, start + n_frames, chunk):
            yield first, self.frames(first, min(first + chunk, start + n_frames))


def _screens_side_by_side(atmosphere: Atmosphere, grid: ActuatorGrid, frame_period_s: float, seed: int, stream: str,
                          n_realisations: int) -> dict[tuple[int, int], object]:
    """``{(realisation, layer): screen}``: the frozen-flow screens of the ``exact`` layers (not boiling) of every
    realisation, built side by side when two or more are non-lattice winds (:func:`build_screens`: the same numbers
    as one after the other, each from its own seed); ``{}`` otherwise (each layer is then built where it is used)."""
    if atmosphere.model != "exact":
        return {}
    keys, calls = [], []
    for r in range(n_realisations):
        for i, lay in enumerate(atmosphere.layers):
            if not lay.boiling_time_s:
                keys.append((r, i))
                calls.append((grid, atmosphere.layer_r0_m(lay), atmosphere.r0_wavelength_m, atmosphere.outer_scale_m,
                              lay.wind_speed_mps, lay.wind_direction_deg, frame_period_s, atmosphere.sensing_kernel,
                              atmosphere.screen_frames, stream_seed(seed, stream, r, i)))
    if sum(lattice_direction(call[5]) is None for call in calls) < 2:
        return {}
    return dict(zip(keys, build_screens(calls), strict=True))


def _layer_generator(atmosphere: Atmosphere, grid: ActuatorGrid, layer: Layer, frame_period_s: float,
                     seed: np.random.SeedSequence):
    """One realisation of one layer, built by ``atmosphere.model``: anything with ``frames(start, stop, basis)``
    (``write_frames(start, stop, out, add)`` for model ``exact``)."""
    r0_m, wavelength_m, outer_m = atmosphere.layer_r0_m(layer), atmosphere.r0_wavelength_m, atmosphere.outer_scale_m
    if atmosphere.model == "exact":
        def screen(child: np.random.SeedSequence):
            return frozen_flow_layer(grid, r0_m, wavelength_m, outer_m, layer.wind_speed_mps, layer.wind_direction_deg,
                                   frame_period_s, atmosphere.sensing_kernel, atmosphere.screen_frames, child)
        if not layer.boiling_time_s:
            return screen(seed)
        # Boiling: a second realisation (sub-stream 1) and the mixing angle's walk (sub-stream 2).
        return BoilingLayer((screen(seed), screen(sub_seed(seed, 1))), layer.boiling_time_s, frame_period_s,
                            sub_seed(seed, 2))
    # The HCIPy models import HCIPy and scipy (seconds): only when a layer of theirs is built, not with the config.
    if atmosphere.model == "hcipy_pupil":
        from eofnn.sim.atmosphere.hcipy_pupil import HcipyPupilLayer

        return HcipyPupilLayer(grid, r0_m, wavelength_m, outer_m, layer.wind_speed_mps, layer.wind_direction_deg,
                               frame_period_s, seed)
    from eofnn.sim.atmosphere.strip import FrozenFlowStrip

    return FrozenFlowStrip(grid.positions_m, grid.pitch_m / atmosphere.oversampling, r0_m, wavelength_m, outer_m,
                           layer.wind_speed_mps, layer.wind_direction_deg, frame_period_s,
                           atmosphere.interpolation_order, seed)
