"""One AO system built in eofnn (its geometric Shack-Hartmann loop) and in OOPAO, and the runs that compare them.

:class:`ShSystem` is the system (subapertures across, diameter, r0 at 500 nm, outer scale, one frozen-flow layer,
frame rate, delay, guide-star magnitude in I band) and builds it in both simulators:

- **OOPAO** (:class:`~eofnn.interop.oopao.OopaoLoop`): ``N`` subapertures of ``d = D / N`` across the pupil ``D``,
  a Fried DM of ``N + 1`` actuators across at the subaperture corners (pitch ``d``, actuators to ``D / 2 + 0.75 d``
  from the centre), the diffractive SH on ``m`` pupil pixels per subaperture (4: 4 x 4 detector pixels of
  ``lambda / d``, centre of gravity), subapertures at least half lit;
- **eofnn** (a :class:`~eofnn.sim.scenario.Scenario` with ``sensor.kind: shack_hartmann``): the actuator grid of
  ``N + 1`` across at the same pitch ``d`` (``diameter_m = (N + 1) d``), so the actuators lie where OOPAO's do and
  the ``N`` Fried subapertures span the same ``D x D`` square; the pupil is the grid's, ``(N + 1) d`` across (half
  a pitch wider than OOPAO's on each side), actuators to ``(N + 1) d / 2``, subapertures whose four corners are
  actuators, ``m`` fine intervals per subaperture side. The detector copies OOPAO's: I band, throughput 1 (OOPAO
  counts every photon), ``m`` pixels across at one pixel per ``lambda / d``, no read noise. Tip and tilt stay in
  the phase (``remove_ptt: false``), as in OOPAO's; the wind blows along a lattice axis in both.

No choice lines up everything with ``pupil="grid"`` (the default): a Fried grid of pitch ``d`` in eofnn has its
pupil where its actuators end, so its outer half pitch lies beyond the subapertures (neither sensed nor well fitted)
and its rim subapertures see the whole phase; OOPAO's pupil ends with its subapertures, whose rim ones are partly lit
and whose DM reaches past it. ``pupil="oopao"`` builds OOPAO's in eofnn: the lit pupil ``D`` (``sensor.
pupil_diameter_m``), the actuators within ``D / 2 + 0.7533 d`` (``grid.active_diameter_m``, OOPAO's
``DeformableMirror`` rule), subapertures valid when at least half lit (``sensor.lit_fraction: 0.5``, OOPAO's
``lightRatio``), a partly lit one measuring its lit area's mean gradient; the same actuators and subapertures as
OOPAO's (357 and 316 at 20 across: ``tests/test_interop_sh_system.py``).

The same residual is scored in both: the piston-removed RMS over each one's pupil (OOPAO's ``np.std(tel.OPD)``),
median over the frames after ``settle_frames``. Both loops close with a plain integrator, ``y(n) = y(n-1) - g
wfs(n-2)`` (two frames of delay in both: :func:`~eofnn.interop.loop.run_closed_loop` and eofnn's plant), and the
error budget splits its residual the same way in both (:mod:`eofnn.evaluation.budget`): runs with the sensor
noise-free and perfect (the least-squares DM fit of the phase over the pupil: no aliasing), and the fitting error
(the phase minus that fit).

``turbulence="eofnn"`` runs OOPAO's sensor, DM and pupil on eofnn's exact frozen flow sampled on OOPAO's pixels
(:func:`eofnn_opd_source`), which tells the sensors apart from the atmospheres.
:mod:`eofnn.studies.sh_compare` runs the comparison.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from eofnn.errors import require
from eofnn.interop.loop import MAX_EXTRA_GAINS, IntegratorControl, run_closed_loop
from eofnn.lazy import lazy_module
from eofnn.validation import POSITIVE, Constraint, Interval, OneOf, check_value, validated

torch = lazy_module("torch")

#: The photometric band of OOPAO's adapter (``Source(optBand="I")``), used by both.
BAND = "I"
#: OOPAO's r0 is given at 500 nm.
R0_WAVELENGTH_M = 500e-9
TURBULENCES = ("oopao", "eofnn")
#: eofnn's pupil for the system: its actuator grid's, or OOPAO's (module docstring).
PUPILS = ("grid", "oopao")
#: OOPAO's Fried DM keeps the actuators within ``D / 2 + OOPAO_ACTUATOR_REACH d`` of the centre
#: (``OOPAO/DeformableMirror.py``), and its Shack-Hartmann the subapertures at least ``OOPAO_LIGHT_RATIO`` lit.
OOPAO_ACTUATOR_REACH = 0.7533
OOPAO_LIGHT_RATIO = 0.5


@dataclass(frozen=True)
@validated
class ShSystem:
    """One AO system, to be built in OOPAO and in eofnn (module docstring for how each is built).

    Parameters
    ----------
    n_subapertures : int
        ``N``: Shack-Hartmann subapertures across the pupil.
    diameter_m : float
        ``D``: OOPAO's telescope diameter (m); the subaperture and actuator pitch is ``D / N`` in both.
    r0_m : float
        Fried parameter at 500 nm (m).
    outer_scale_m, wind_speed_mps : float
        The single frozen-flow layer (wind along a lattice axis in both).
    frame_rate_hz : float
        Loop rate.
    delay_frames : int
        Loop delay (frames).
    samples_per_subaperture : int
        ``m``: OOPAO's pupil pixels per subaperture (hence its SH's detector pixels across) and eofnn's fine-grid
        intervals per subaperture side.
    pupil : {"grid", "oopao"}
        eofnn's pupil: its actuator grid's (``(N + 1) d`` across), or OOPAO's (module docstring).
    """

    n_subapertures: int = 20
    diameter_m: float = 8.0
    r0_m: float = 0.15
    outer_scale_m: float = 25.0
    wind_speed_mps: float = 10.0
    frame_rate_hz: float = 1000.0
    delay_frames: int = 2
    samples_per_subaperture: int = 4
    pupil: str = "grid"

    _constraints: ClassVar[dict[str, Constraint]] = {
        "n_subapertures": Interval(4, 100, integer=True, unit="subapertures across"),
        "diameter_m": Interval(0, 100, closed="right", unit="m"),
        "r0_m": Interval(0, 10, closed="right", unit="m at 500 nm"),
        "outer_scale_m": Interval(0, 1e4, closed="right", unit="m"),
        "wind_speed_mps": Interval(0, 100, unit="m/s"),
        "frame_rate_hz": POSITIVE,
        "delay_frames": Interval(1, 10, integer=True, unit="frames"),
        "samples_per_subaperture": Interval(2, 16, integer=True, unit="pixels per subaperture"),
        "pupil": OneOf(PUPILS),
    }

    @property
    def pitch_m(self) -> float:
        """``d``: the subaperture side and the actuator pitch (m), the same in both."""
        return self.diameter_m / self.n_subapertures

    def detector(self, magnitude: float, spot_fwhm_lambda_over_d: float = 1.0) -> dict:
        """eofnn's detector copying OOPAO's SH: band I, all photons, ``m`` pixels of ``lambda / d``, and (by
        default) a diffraction-limited spot; the photon noise per slope is proportional to the spot's FWHM."""
        return {"band": BAND, "magnitude": float(magnitude), "throughput": 1.0,
                "pixels_across": self.samples_per_subaperture, "pixels_per_lambda_over_d": 1.0,
                "spot_fwhm_lambda_over_d": float(spot_fwhm_lambda_over_d)}

    def eofnn_scenario(self, magnitude: float | None, screen_frames: int, spot_fwhm_lambda_over_d: float = 1.0):
        """The system in eofnn (``magnitude`` None: no photon noise)."""
        from eofnn.sim.scenario import Scenario

        n = self.n_subapertures + 1
        detector = {} if magnitude is None else {"detector": self.detector(magnitude, spot_fwhm_lambda_over_d)}
        sensor = {"kind": "shack_hartmann", "samples_per_subaperture": self.samples_per_subaperture, **detector}
        grid = {"diameter_m": n * self.pitch_m, "n_across": n, "obstruction": 0.0}
        if self.pupil == "oopao":
            sensor.update(pupil_diameter_m=self.diameter_m, lit_fraction=OOPAO_LIGHT_RATIO)
            grid["active_diameter_m"] = self.diameter_m + 2 * OOPAO_ACTUATOR_REACH * self.pitch_m
        return Scenario.from_dict({
            "grid": grid,
            "atmosphere": self._atmosphere(screen_frames),
            "frame_rate_hz": self.frame_rate_hz, "plant": {"delay_frames": self.delay_frames}, "sensor": sensor})

    def _atmosphere(self, screen_frames: int) -> dict:
        return {"r0_m": self.r0_m, "r0_wavelength_m": R0_WAVELENGTH_M, "outer_scale_m": self.outer_scale_m,
                "layers": [{"wind_speed_mps": self.wind_speed_mps, "wind_direction_deg": 0.0}],
                "remove_ptt": False, "screen_frames": screen_frames}

    def oopao(self, sensor: str = "shack_hartmann", magnitude: float = 8.0, photon_noise: bool = False,
              turbulence: str = "oopao", screen_frames: int = 2000):
        """The system in OOPAO (``turbulence="eofnn"``: on eofnn's frozen flow, :func:`eofnn_opd_source`)."""
        from eofnn.interop.oopao import OopaoLoop

        check_value("turbulence", turbulence, OneOf(TURBULENCES))
        source = None
        if turbulence == "eofnn":
            source = eofnn_opd_source(self, self.n_subapertures * self.samples_per_subaperture, screen_frames)
        return OopaoLoop(self.n_subapertures, self.diameter_m, pupil_pixels_per_subaperture=self.samples_per_subaperture,
                         sensor=sensor, photon_noise=photon_noise, magnitude=magnitude, r0_m=self.r0_m,
                         outer_scale_m=self.outer_scale_m, wind_speed_mps=self.wind_speed_mps,
                         frame_rate_hz=self.frame_rate_hz, delay_frames=self.delay_frames, opd_source=source)


def eofnn_opd_source(system: ShSystem, resolution: int, screen_frames: int):
    """``source(seed)``: eofnn's exact frozen flow of ``system`` on a ``resolution`` x ``resolution`` grid of pitch
    ``D / resolution`` (OOPAO's pixels), one map (nm) per frame, from the stream ``"oopao-pixels"`` of ``seed``."""
    from eofnn.sim.atmosphere.turbulence import Atmosphere, Turbulence
    from eofnn.sim.grid import ActuatorGrid
    from eofnn.validation import from_mapping

    pixel = system.diameter_m / resolution
    grid = ActuatorGrid((resolution + 2) * pixel, resolution + 2)  # one pixel of margin: the pupil's disc inside
    atmosphere = from_mapping(Atmosphere, {**system._atmosphere(screen_frames), "kernel": "point"}, "atmosphere")

    def source(seed: int):
        turbulence = Turbulence(atmosphere, grid, system.frame_rate_hz, seed, "oopao-pixels")
        for _, chunk in turbulence.chunks(screen_frames, 256):
            for frame in grid.to_map(chunk[0], fill=0.0).numpy():
                yield frame[1:-1, 1:-1]

    return source


# -- runs ---------------------------------------------------------------------------------------------------
def eofnn_runs(scenario, gain: float, seed: int, realisations: int, frames: int, settle_frames: int,
               isolates=("none", "noise_free", "perfect"), inner_diameter_m: float | None = None
               ) -> dict[str, list[float | None]]:
    """The integrator of ``gain`` in eofnn's loop on ``realisations`` realisations of the test stream of ``seed``,
    once per ``isolate``: ``{isolate: [median pupil residual (nm) per realisation, None if diverged]}``, and
    ``"fitting"``: the median fitting error of each realisation. ``"inner:<isolate>"`` and ``"inner:fitting"``:
    the same scored over the disc of ``inner_diameter_m`` (OOPAO's pupil) only, every
    :data:`~eofnn.sim.loop.sensing.PHASE_EVERY`-th frame."""
    from eofnn.control.baselines import Integrator
    from eofnn.sim.loop.runner import run_loop
    from eofnn.sim.loop.sensing import PHASE_EVERY

    out = {}
    for isolate in isolates:
        turbulence = scenario.turbulence(seed, "test", realisations, isolate=isolate)
        inner = _inner_mask(turbulence, inner_diameter_m)
        kept = []

        def score(first: int, arrays: dict, kept=kept, inner=inner) -> None:
            for frame in range(first + (-first) % PHASE_EVERY, first + arrays["y"].shape[1], PHASE_EVERY):
                if frame >= settle_frames:
                    kept.append(_piston_free_rms(arrays["pupil_residual"](frame)[:, inner]))

        result = run_loop(turbulence, scenario.plant, Integrator(gain), frames, noise_seed=seed, record=(),
                          progress=False, on_chunk=None if inner is None else score)
        rms = result.pupil_residual_rms_nm[:, settle_frames:]
        out[isolate] = [None if result.diverged else float(r.median()) for r in rms]
        if inner is not None:
            out[f"inner:{isolate}"] = [None if result.diverged else float(r.median())
                                       for r in torch.stack(kept, 1)]
    turbulence = scenario.turbulence(seed, "test", realisations)
    ops = turbulence.operators
    products = turbulence.products(settle_frames, frames)
    fit = ops.pupil_rms(products["z"], products["sum"], products["sumsq"], -products["fit"])
    out["fitting"] = [float(r.median()) for r in fit]
    inner = _inner_mask(turbulence, inner_diameter_m)
    if inner is not None:
        frames_kept = range(settle_frames + (-settle_frames) % PHASE_EVERY, frames, PHASE_EVERY)
        values = [_piston_free_rms((turbulence.phase_at(n) + ops.surface(-products["fit"][:, n - settle_frames])
                                    )[:, ops.pupil][:, inner]) for n in frames_kept]
        out["inner:fitting"] = [float(r.median()) for r in torch.stack(values, 1)]
    return out


def _inner_mask(turbulence, diameter_m: float | None):
    """Boolean over the pupil's fine points: those within ``diameter_m`` of the centre (None: no inner score)."""
    if diameter_m is None:
        return None
    positions = turbulence.operators.sensor.geometry.fine_positions_m[turbulence.operators.pupil]
    return torch.as_tensor(np.hypot(*positions.T) <= diameter_m / 2 + 1e-9 * diameter_m)


def _piston_free_rms(values):
    """``(R, points)`` -> ``(R,)``: the RMS over the points with the mean removed."""
    return (values - values.mean(-1, keepdim=True)).pow(2).mean(-1).sqrt()


def eofnn_gain_scan(scenario, gains, seed: int, frames: int, settle_frames: int) -> dict:
    """``{"gain": best, "scan": {gain: median or None}}`` on the ``"scan"`` stream of ``seed`` (not the test one)."""
    from eofnn.control.baselines import Integrator

    scan = {}

    def run(gain: float) -> None:
        scan[gain] = scenario.median_residual_nm(Integrator(gain), frames, seed, "scan", settle_frames)

    for g in gains:
        run(float(g))
    step = sorted(scan)[-1] - sorted(scan)[-2]
    for _ in range(MAX_EXTRA_GAINS):  # climb past the grid's top while it is the best, as scan_integrator does
        stable = {g: v for g, v in scan.items() if v is not None}
        require(bool(stable), f"every integrator gain of {list(scan)} diverged in eofnn's loop: give smaller gains")
        if min(stable, key=stable.get) != max(scan):
            break
        run(round(max(scan) + step, 6))
    stable = {g: v for g, v in scan.items() if v is not None}
    return {"gain": min(stable, key=stable.get), "scan": scan}


def oopao_medians(sim, gain: float, seeds, frames: int, settle_frames: int) -> list[float | None]:
    """The integrator of ``gain`` in ``sim``'s loop on each of ``seeds``: median residual (nm) or None."""
    return [run_closed_loop(sim, IntegratorControl(gain), frames, int(seed)).metrics(settle_frames).median_rms_nm
            for seed in seeds]


def oopao_fitting(sim, seeds, frames: int, settle_frames: int, every: int = 5) -> list[float]:
    """The median fitting error of each of ``seeds`` (frames ``settle_frames`` on, every ``every``-th)."""
    from eofnn.interop.oopao import fitting_error

    return [fitting_error(sim, frames, int(seed), every, start=settle_frames)["median_rms_nm"] for seed in seeds]


def budget_terms(total, noise_free, perfect, fitting) -> dict[str, list[float | None]]:
    """Per realisation, :func:`eofnn.evaluation.budget.error_budget`'s terms (nm) from the runs' medians."""
    from eofnn.evaluation.budget import error_budget

    terms = [error_budget(*runs) for runs in zip(total, noise_free, perfect, fitting, strict=True)]
    keys = ("fitting_nm", "aliasing_nm", "noise_nm", "temporal_nm")
    return {k[:-3]: [t[k] for t in terms] for k in keys}


def spread(values) -> dict:
    """``{"mean", "std", "values"}`` of per-realisation values (None where one diverged)."""
    finite = [v for v in values if v is not None]
    if len(finite) < len(values) or not finite:
        return {"mean": None, "std": None, "values": list(values)}
    return {"mean": float(np.mean(finite)), "std": float(np.std(finite, ddof=1)) if len(finite) > 1 else 0.0,
            "values": [float(v) for v in finite]}
