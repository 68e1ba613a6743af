"""A scenario: telescope (actuator grid), atmosphere, frame rate and plant — everything a loop runs in."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

import yaml

from eofnn.errors import ConfigError
from eofnn.resources import require_memory
from eofnn.seeding import int_seed
from eofnn.sim.atmosphere.anywind import screen_bytes
from eofnn.sim.atmosphere.changes import layer_winds, strongest_cn2_scale
from eofnn.sim.atmosphere.disturbances import Vibration, build_vibrations
from eofnn.sim.atmosphere.turbulence import Atmosphere, Turbulence
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.loop.plant import Plant
from eofnn.sim.loop.runner import Controller, run_loop
from eofnn.sim.loop.sensing import ShackHartmannTurbulence, loop_operators
from eofnn.sim.sensing.constants import PYRAMID_MIN_R0_SAMPLES
from eofnn.sim.sensing.sensor import PYRAMID_ONLY, Sensor, build_sensor
from eofnn.validation import Constraint, Interval, from_mapping, validated


@dataclass(frozen=True)
class Change:
    """One change of a scenario in time (:meth:`Scenario.changes`): its name, and the frames it starts and ends at."""

    name: str
    start_frame: int
    end_frame: int


@dataclass(frozen=True)
@validated
class Scenario:
    """Where a controller is evaluated or its training data recorded.

    Parameters
    ----------
    grid : ActuatorGrid
        Telescope diameter and DM actuators.
    atmosphere : Atmosphere
        Turbulence profile.
    frame_rate_hz : float
        Loop frame rate in Hz.
    plant : Plant
        Loop delay and model errors (the one home of the delay: everything else derives it from here).
    vibrations : list of Vibration
        Telescope vibrations added to the turbulence ``s(n)`` (after the atmosphere's piston/tip/tilt removal, so
        they are seen): e.g. ``[{mode: tip, frequency_hz: 40, amplitude_nm: 30, damping: 0.01}]``; fields in
        :class:`~eofnn.sim.atmosphere.disturbances.Vibration`. None by default.
    sensor : Sensor
        The wavefront sensor (:class:`~eofnn.sim.sensing.sensor.Sensor`): ``{kind: subaperture}`` (the default, the
        zonal average at each actuator) or ``{kind: shack_hartmann, detector: {magnitude: 8, ...}, ...}`` (slopes,
        reconstructor, photon noise, and the residual over the pupil: :mod:`eofnn.sim.loop.sensing`).
    """

    grid: ActuatorGrid = field(default_factory=ActuatorGrid)
    atmosphere: Atmosphere = field(default_factory=Atmosphere)
    frame_rate_hz: float = 1000.0
    plant: Plant = field(default_factory=Plant)
    vibrations: list[Vibration] = field(default_factory=list)
    sensor: Sensor = field(default_factory=Sensor)

    _constraints: ClassVar[dict[str, Constraint]] = {"frame_rate_hz": Interval(0, 1e6, closed="right", unit="Hz")}

    def __post_init__(self) -> None:
        for name, cls in (("grid", ActuatorGrid), ("atmosphere", Atmosphere), ("plant", Plant)):
            value = getattr(self, name)
            if isinstance(value, dict):
                object.__setattr__(self, name, _build(cls, value, name))
            elif not isinstance(value, cls):
                raise ConfigError(f"{name}={value!r} is invalid: it must be a mapping of {cls.__name__} fields")
        object.__setattr__(self, "vibrations", build_vibrations(self.vibrations, self.frame_rate_hz))
        object.__setattr__(self, "sensor", build_sensor(self.sensor))
        if self.sensor.is_shack_hartmann:
            self._check_shack_hartmann()
        elif self.sensor.is_pyramid:
            self._check_pyramid()
        for axis in ("x", "y"):  # the plant's own limit is +-10 pitches whatever the grid
            shift = getattr(self.plant, f"misregistration_{axis}")
            if abs(shift) >= self.grid.n_across:
                raise ConfigError(f"plant.misregistration_{axis}={shift!r} is invalid: it shifts the DM by more than "
                                  f"the grid's {self.grid.n_across} actuators across: it must be within "
                                  f"+-{self.grid.n_across - 1} (actuator pitches)")

    @property
    def turbulence_grid(self) -> ActuatorGrid:
        """Where the turbulence is synthesised: the actuators, a Shack-Hartmann's fine grid or a pyramid's pupil
        points."""
        if self.sensor.is_shack_hartmann:
            return loop_operators(self.grid, self.sensor.shack_hartmann()).sensor.geometry.fine_grid
        if self.sensor.is_pyramid:
            from eofnn.sim.sensing.pyramid import pupil_grid

            return pupil_grid(self.grid, self.sensor.pyramid())
        return self.grid

    @property
    def delay_frames(self) -> int | float:
        """The loop delay in frames (the plant's; fractional allowed)."""
        return self.plant.delay_frames

    def turbulence(self, seed: int, stream: str = "test", n_realisations: int = 1,
                   isolate: str = "none") -> Turbulence | ShackHartmannTurbulence:
        """The turbulence stream of this scenario for ``seed`` and ``stream`` (a Shack-Hartmann scenario's carries its
        sensor; ``isolate`` makes it noise-free or perfect for the error budget, :mod:`eofnn.sim.loop.sensing`; a
        pyramid scenario's reads its phase over the pupil each frame, :mod:`eofnn.sim.loop.pyramid`)."""
        if self.sensor.is_pyramid:
            from eofnn.sim.loop.pyramid import PyramidTurbulence

            return PyramidTurbulence(self.atmosphere, self.grid, self.frame_rate_hz, seed, stream, n_realisations,
                                     self.vibrations, self.sensor, isolate)
        if self.sensor.is_shack_hartmann:
            return ShackHartmannTurbulence(self.atmosphere, self.grid, self.frame_rate_hz, seed, stream,
                                           n_realisations, self.vibrations, self.sensor, isolate)
        return Turbulence(self.atmosphere, self.grid, self.frame_rate_hz, seed, stream, n_realisations,
                          self.vibrations, self.sensor.registered)

    def _check_phase_sampling(self) -> None:
        """Refuse, in one line each, an atmosphere a sensor that samples the phase at points cannot run."""
        atm, kind = self.atmosphere, self.sensor.kind
        if atm.model != "exact":
            raise ConfigError(f"atmosphere.model={atm.model!r} is invalid with sensor.kind {kind}: its phase is "
                              "synthesised exactly on the sensor's own points; use model 'exact'")
        if atm.kernel not in (None, "point"):
            raise ConfigError(f"atmosphere.kernel={atm.kernel!r} is invalid with sensor.kind {kind}: the "
                              "zonal kernel is the subaperture sensor's; this sensor samples the phase at "
                              "points of its own grid (remove kernel, or set it to point)")

    def _check_pyramid(self) -> None:
        """Refuse, in one line each, what a pyramid scenario cannot run (its calibration waits for its first loop)."""
        self._check_phase_sampling()
        pupil = self.turbulence_grid  # the pupil's checks: diameter, points across, modulation
        config = self.sensor.pyramid()
        atm = self.atmosphere  # r0 at its smallest over the run: after the changes that strengthen the Cn2 most
        strongest = strongest_cn2_scale(atm.layers, atm.changes)
        r0_m = atm.r0_m * strongest ** (-3 / 5) * (config.wavelength_nm * 1e-9 / atm.r0_wavelength_m) ** 1.2
        if r0_m < PYRAMID_MIN_R0_SAMPLES * pupil.pitch_m:  # the focal plane (n lambda/D) holds 1.5 seeing widths
            spp = config.samples_per_pixel
            need = math.ceil(PYRAMID_MIN_R0_SAMPLES * pupil.pitch_m * spp / r0_m)
            need += (need * pupil.n_across // spp) % 2  # pixels x samples even
            raise ConfigError(
                f"sensor.samples_per_pixel={spp} is invalid here: the pupil is sampled every {pupil.pitch_m:.3g} m "
                f"against r0 = {r0_m:.3g} m at the sensing wavelength ({config.wavelength_nm:g} nm"
                f"{'' if strongest <= 1 else f', after atmosphere.changes scale the Cn2 by {strongest:.3g}'}), and r0 must span "
                f"at least {PYRAMID_MIN_R0_SAMPLES:g} samples (else the seeing halo wraps round the simulated focal "
                f"plane and the loop does not close): raise samples_per_pixel to {need} or more")

    def _check_shack_hartmann(self) -> None:
        """Refuse, in one line each, what a Shack-Hartmann scenario cannot run."""
        self._check_phase_sampling()
        self.sensor.check_fits(self.grid)
        loop_operators(self.grid, self.sensor.shack_hartmann())  # builds the geometry and R: their checks too

    def median_residual_nm(self, controller: Controller, n_frames: int, seed: int, stream: str, settle_frames: int, *,
                           realisations: int = 1, plant: Plant | None = None, divergence_factor: float = 10.0,
                           on_chunk=None) -> float | None:
        """Close the loop with ``controller`` for ``n_frames`` on stream ``stream`` of ``seed`` (a stream of its own,
        WFS noise included), in this scenario's plant or ``plant``: the median residual RMS (nm) after
        ``settle_frames`` (over the pupil in a Shack-Hartmann scenario), ``None`` when the loop diverged. How tuning
        scans and robustness probes judge a setting."""
        result = run_loop(self.turbulence(seed, stream, realisations), plant or self.plant, controller, n_frames,
                          noise_seed=int_seed(seed, stream), record=(), divergence_factor=divergence_factor,
                          progress=False, on_chunk=on_chunk)
        if result.diverged:
            return None
        rms = result.residual_rms_nm if result.pupil_residual_rms_nm is None else result.pupil_residual_rms_nm
        return float(rms[:, settle_frames:].median())

    def require_stream_frames(self, n_frames: int, what: str, realisations: int = 1) -> None:
        """Refuse, up front, a stream of ``n_frames`` frames (of ``realisations`` realisations side by side) that the
        ``exact`` turbulence screen cannot hold or whose screens do not fit memory."""
        atm = self.atmosphere
        if atm.model == "exact" and n_frames > atm.screen_frames:
            raise ConfigError(f"{what} needs {n_frames} frames of one turbulence realisation but "
                              f"atmosphere.screen_frames={atm.screen_frames} (model exact): raise "
                              f"atmosphere.screen_frames to at least {n_frames}, or use shorter streams")
        grid = self.turbulence_grid
        if atm.model == "exact":  # a non-lattice wind builds its whole screen at once: refuse what cannot fit
            winds = [w for i, lay in enumerate(atm.layers)
                     for w in [lay, *layer_winds(lay, [c for c in atm.changes if c.layer == i])]]
            peaks = [screen_bytes(grid, atm.outer_scale_m, w.wind_speed_mps, w.wind_direction_deg,
                                  1 / self.frame_rate_hz, atm.screen_frames) for w in winds]
            # One screen is being built at a time; every realisation keeps each built screen while it streams.
            n_screens = realisations * sum(1 for peak in peaks if peak)
            need = max(peaks) + (n_screens - 1) * 4 * atm.screen_frames * grid.n_actuators
            if n_screens:
                require_memory(need, f"{what}: the set of exact screens of non-lattice winds ({n_screens} screen(s) "
                                     f"of {grid.n_actuators} {'actuators' if self.sensor.kind == 'subaperture' else 'points'} x "
                                     f"screen_frames={atm.screen_frames})")

    def changes(self) -> list[Change]:
        """The changes of this scenario (the atmosphere's ``changes`` and the plant's DM gain drift), in time order of
        their end."""
        rate = self.frame_rate_hz
        out = [Change(f"atmosphere.changes[{i}]", round(c.at_s * rate), round((c.at_s + c.ramp_s) * rate))
               for i, c in enumerate(self.atmosphere.changes)]
        drift = self.plant.dm_gain_drift
        if drift is not None:
            out.append(Change("plant.dm_gain_drift", round(drift.start_s * rate), round(drift.stop_s * rate)))
        return sorted(out, key=lambda c: (c.end_frame, c.start_frame))

    def require_changes_within(self, n_frames: int, what: str) -> None:
        """Refuse, in one line, a change (wind, DM-gain drift) that starts after a run of ``n_frames`` ends: it would
        change nothing, and a study of it would report a stationary run as if it had changed."""
        rate = self.frame_rate_hz
        for change in self.changes():
            if change.start_frame >= n_frames:
                raise ConfigError(f"{what}: {change.name} starts at {change.start_frame / rate:g} s (frame "
                                  f"{change.start_frame}), after the run of {n_frames} frames ({n_frames / rate:g} s "
                                  f"at {rate:g} Hz) ends: start it earlier or run longer")

    def with_plant(self, **changes: Any) -> Scenario:
        """A copy whose plant has some fields changed (the same sky and telescope)."""
        return replace(self, plant=self.plant.with_errors(**changes))

    def to_dict(self) -> dict:
        out = asdict(self)
        out["atmosphere"]["layers"] = [dict(lay) for lay in out["atmosphere"]["layers"]]
        out["vibrations"] = [dict(vib) for vib in out["vibrations"]]
        if self.sensor.kind == "subaperture":  # the default sensor: configs written before it existed still match
            del out["sensor"]
        else:  # a Shack-Hartmann's config written before the pyramid existed still matches
            out["sensor"] = {k: v for k, v in out["sensor"].items() if k not in PYRAMID_ONLY or v is not None}
        return out

    @classmethod
    def from_dict(cls, config: dict) -> Scenario:
        return _build(cls, config, "scenario")

    @classmethod
    def from_yaml(cls, path: str | Path) -> Scenario:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"scenario file {str(path)!r} does not exist")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except (yaml.YAMLError, UnicodeDecodeError) as err:
            raise ConfigError(f"scenario file {str(path)!r} is not valid YAML ({type(err).__name__})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"scenario file {str(path)!r} must hold a mapping of scenario fields")
        return cls.from_dict(data.get("scenario", data))


def _build(cls, config: dict, where: str):
    """Instantiate a config dataclass, turning unknown keys into one clear line (the atmosphere builds its layers)."""
    if not isinstance(config, dict):
        raise ConfigError(f"{where} must be a mapping, got {type(config).__name__}")
    return from_mapping(cls, config, where)
