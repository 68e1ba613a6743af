"""eofnn's modulated pyramid loop against OOPAO's (``OopaoLoop(sensor="pyramid")``) on one system built alike in both.

:class:`PyramidSystem` is the system: ``N`` detector pixels across each pupil image of ``D``, ``m`` pupil points per
pixel, a Fried DM of ``N + 1`` actuators across at pitch ``d = D / N`` (Gaussian influence functions of the same
coupling), modulation ``r`` lambda/D in I band, slopes maps, one frozen-flow layer, a two-frame delay:

- **OOPAO**: :class:`~eofnn.interop.oopao.OopaoLoop` with ``sensor="pyramid"`` (``OOPAO.Pyramid``,
  :mod:`eofnn.interop.oopao_pyramid`), the reconstructor the truncated pseudo-inverse of its push-pull interaction
  matrix (singular values below ``relative_cut`` of the largest dropped), on eofnn's exact frozen flow sampled on
  OOPAO's pixels (:func:`~eofnn.studies.sh_system.eofnn_opd_source`): the same turbulence model in both;
- **eofnn**: a scenario with ``sensor.kind: pyramid`` on the actuator grid of ``N + 1`` across at pitch ``d``
  (the actuators where OOPAO's are, those within ``D / 2 + 0.7533 d`` kept as OOPAO keeps them), the lit pupil
  ``D`` (``pupil_diameter_m``) sampled on ``N m`` points across as OOPAO's telescope, ``N`` pixels across, the same
  relative cut. OOPAO's tip-tilt modulation spans ``2 pi r`` over ``n - 1`` of its ``n`` pupil samples, so its PSF
  runs on a circle ``n / (n - 1)`` times the radius asked for: eofnn is given that radius
  (``experiments/pyramid/README.md`` measures it).

Both normalise the same way: slopes maps (``s_x``, ``s_y`` over the valid pixels), divided by the mean flux per
valid pixel of the four images, per frame; so a response is per nm of command in both, flux-free. Each picks its
valid pixels by its own rule (``lightRatio`` 0.1 of a frame modulated at 50 lambda/D); the comparison says how many.

Measured (:func:`compare`): the interaction matrix's response per Karhunen-Loeve command mode (``|D k_m|``, eofnn's
over OOPAO's, the modes of :func:`~eofnn.sim.sensing.optical_gains.kl_modes` mapped between the two actuator orders
by position), each best-gain integrator's median residual over its pupil, and the optical gains of the same modes
about each loop's own residual (eofnn's :class:`~eofnn.sim.sensing.optical_gains.OpticalGainProbe`; OOPAO's pyramid
probed by the same method, :func:`~eofnn.interop.oopao_pyramid.probe_optical_gains`) and, crossed, about the other
loop's residual; beside them OOPAO's ``GainSensingCamera`` about OOPAO's residuals (its convolutional model).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np

from eofnn.studies.sh_system import OOPAO_ACTUATOR_REACH, ShSystem, eofnn_opd_source
from eofnn.validation import POSITIVE, Constraint, Interval, validated


@dataclass(frozen=True)
@validated
class PyramidSystem:
    """One pyramid AO system, to be built in OOPAO and in eofnn (module docstring).

    Parameters
    ----------
    n_subapertures : int
        ``N``: detector pixels across each pupil image (the Fried DM has ``N + 1`` actuators across).
    diameter_m : float
        ``D``: the lit pupil (m).
    samples_per_pixel : int
        ``m``: pupil points per detector pixel (OOPAO's pixels per subaperture).
    modulation_lambda_over_d : float
        The modulation radius asked of OOPAO (lambda/D in I band).
    r0_m, outer_scale_m, wind_speed_mps : float
        The single frozen-flow layer (r0 at 500 nm; wind along a lattice axis).
    frame_rate_hz : float
    delay_frames : int
    relative_cut : float
        Both reconstructors drop the singular values below this fraction of the largest.
    """

    n_subapertures: int = 16
    diameter_m: float = 4.0
    samples_per_pixel: int = 2
    modulation_lambda_over_d: float = 3.0
    r0_m: float = 0.15
    outer_scale_m: float = 25.0
    wind_speed_mps: float = 10.0
    frame_rate_hz: float = 1000.0
    delay_frames: int = 2
    relative_cut: float = 0.1

    _constraints: ClassVar[dict[str, Constraint]] = {
        "n_subapertures": Interval(4, 64, integer=True, unit="pixels across"),
        "diameter_m": Interval(0, 100, closed="right", unit="m"),
        "samples_per_pixel": Interval(2, 8, integer=True, unit="pupil points per pixel"),
        "modulation_lambda_over_d": Interval(0, 20, unit="lambda/D"),
        "r0_m": Interval(0, 10, closed="right", unit="m at 500 nm"),
        "outer_scale_m": Interval(0, 1e4, closed="right", unit="m"),
        "wind_speed_mps": Interval(0, 100, unit="m/s"),
        "frame_rate_hz": POSITIVE,
        "delay_frames": Interval(1, 10, integer=True, unit="frames"),
        "relative_cut": Interval(0.001, 1, closed="left"),
    }

    @property
    def pupil_points(self) -> int:
        """``n = N m``: pupil points across in both."""
        return self.n_subapertures * self.samples_per_pixel

    @property
    def eofnn_modulation(self) -> float:
        """The radius eofnn is given: OOPAO's, times ``n / (n - 1)`` (module docstring)."""
        n = self.pupil_points
        return self.modulation_lambda_over_d * n / (n - 1)

    def _sh(self) -> ShSystem:
        """The same telescope and atmosphere as a :class:`ShSystem` (for its turbulence and OOPAO's build)."""
        return ShSystem(self.n_subapertures, self.diameter_m, self.r0_m, self.outer_scale_m, self.wind_speed_mps,
                        self.frame_rate_hz, self.delay_frames, self.samples_per_pixel, pupil="oopao")

    def eofnn_scenario(self, screen_frames: int):
        """The system in eofnn, noise-free."""
        from eofnn.sim.scenario import Scenario

        n, d = self.n_subapertures + 1, self.diameter_m / self.n_subapertures
        sensor = {"kind": "pyramid", "modulation_lambda_over_d": self.eofnn_modulation,
                  "pixels_across": self.n_subapertures, "samples_per_pixel": self.samples_per_pixel,
                  "pupil_diameter_m": self.diameter_m, "relative_cut": self.relative_cut}
        grid = {"diameter_m": n * d, "n_across": n, "obstruction": 0.0,
                "active_diameter_m": self.diameter_m + 2 * OOPAO_ACTUATOR_REACH * d}
        return Scenario.from_dict({"grid": grid, "atmosphere": self._sh()._atmosphere(screen_frames),
                                   "frame_rate_hz": self.frame_rate_hz, "plant": {"delay_frames": self.delay_frames},
                                   "sensor": sensor})

    def oopao(self, screen_frames: int):
        """The system in OOPAO, noise-free, on eofnn's frozen flow."""
        from eofnn.interop.oopao import OopaoLoop

        source = eofnn_opd_source(self._sh(), self.pupil_points, screen_frames)
        return OopaoLoop(self.n_subapertures, self.diameter_m, pupil_pixels_per_subaperture=self.samples_per_pixel,
                         sensor="pyramid", modulation_lambda_over_d=self.modulation_lambda_over_d, r0_m=self.r0_m,
                         outer_scale_m=self.outer_scale_m, wind_speed_mps=self.wind_speed_mps,
                         frame_rate_hz=self.frame_rate_hz, delay_frames=self.delay_frames, rcond=self.relative_cut,
                         opd_source=source)


def actuator_order(eofnn_positions_m: np.ndarray, oopao_positions_m: np.ndarray, pitch_m: float) -> np.ndarray:
    """``index`` with ``eofnn_positions_m[index[j]]`` the actuator at OOPAO's ``j``-th position (the same actuators
    in both; a mismatch is an error, not a nearest guess)."""
    gaps = np.hypot(*(oopao_positions_m[:, None, :] - eofnn_positions_m[None, :, :]).transpose(2, 0, 1))
    index = gaps.argmin(1)
    worst = float(gaps[np.arange(len(index)), index].max())
    if len(eofnn_positions_m) != len(oopao_positions_m) or worst > 1e-6 * pitch_m or len(set(index)) != len(index):
        raise ValueError(f"the actuators differ: eofnn {len(eofnn_positions_m)}, OOPAO {len(oopao_positions_m)}, "
                         f"worst position gap {worst / pitch_m:.3g} pitch")
    return index


def response_ratios(eofnn_sensor, sim, n_modes: int) -> dict:
    """The interaction matrices' responses per Karhunen-Loeve command mode: ``{"ratio": |D_eofnn k| / |D_oopao k|
    per mode, "modes", "valid_pixels": {eofnn, oopao}}`` (both in signal per nm of command, module docstring)."""
    from eofnn.sim.sensing.optical_gains import kl_modes

    grid = eofnn_sensor.grid
    order = actuator_order(np.asarray(grid.positions_m), sim.positions_m, grid.pitch_m)
    modes = kl_modes(grid, min(n_modes, grid.n_actuators - 1))
    ours = np.linalg.norm(np.asarray(eofnn_sensor.interaction_matrix) @ modes, axis=0)
    theirs = np.linalg.norm(sim.interaction_matrix @ modes[order], axis=0)
    return {"ratio": (ours / theirs).tolist(), "modes": modes.shape[1],
            "valid_pixels": {"eofnn": int(eofnn_sensor.signals.n_valid), "oopao": int(sim.wfs.validI4Q.sum())}}


def response_with_oopaos_dm(eofnn_sensor, sim, n_modes: int) -> list[float]:
    """The cause of :func:`response_ratios`'s spread, measured: eofnn's pyramid given OOPAO's own DM surfaces of the
    same modes (``dm.modes``, OOPAO's influence functions on its pixels) in place of its own, ``|D k|`` over
    OOPAO's per mode. OOPAO evaluates its influence functions on pixel coordinates stretched by ``n / (n - 1)``
    (``DeformableMirror.modesComputation``), so its surfaces are not eofnn's Gaussians on the same points."""
    import torch

    from eofnn.sim.sensing.optical_gains import kl_modes

    grid = eofnn_sensor.grid
    order = actuator_order(np.asarray(grid.positions_m), sim.positions_m, grid.pitch_m)
    modes = kl_modes(grid, min(n_modes, grid.n_actuators - 1))[order]
    shapes = np.asarray(sim.dm.modes, dtype=np.float64)[np.asarray(sim.pupil_mask).ravel()] @ modes  # (n_pupil, M)
    ours = np.linalg.norm(eofnn_sensor.response(torch.as_tensor(shapes.T)).numpy(), axis=1)
    theirs = np.linalg.norm(sim.interaction_matrix @ modes, axis=0)
    return (ours / theirs).tolist()


def fitting_errors(scenario, sim, seeds, frames: int, settle_frames: int) -> dict:
    """What each DM cannot correct, the median over the settled frames of the phase minus its least-squares fit by
    the kept modes, mean over the realisations (nm): ``{"eofnn", "oopao"}`` (eofnn's realisations are those of the
    ``"test"`` stream of ``seeds[0]``, OOPAO's the seeds)."""
    from eofnn.interop.oopao import fitting_error

    turbulence = scenario.turbulence(seeds[0], "test", len(seeds))
    products = turbulence.products(settle_frames, frames)
    ops = turbulence.operators
    ours = ops.pupil_rms(products["z"], products["sum"], products["sumsq"], -products["fit"]).median(1).values
    turbulence.release()
    theirs = [fitting_error(sim, frames, int(s), 5, start=settle_frames)["median_rms_nm"] for s in seeds]
    return {"eofnn": float(ours.mean()), "oopao": float(np.mean(theirs))}


def _oopao_residuals(sim, frames: list[int]):
    """An observer for :func:`~eofnn.interop.loop.run_closed_loop` keeping the residual OPD maps (nm) of
    ``frames``; the maps are its ``maps``."""
    res = sim.tel.resolution

    def observe(n: int, sim) -> None:
        if n in frames:
            residual = np.zeros((res, res))
            residual[sim.pupil_mask] = sim.residual_opd_nm()
            observe.maps.append(residual)

    observe.maps = []
    return observe


def compare(system: PyramidSystem, gains, frames: int, settle_frames: int, realisations: int, seed: int,
            n_modes: int = 100, n_gain_modes: int = 50, probe_frames: int = 6, progress=print) -> dict:
    """Every number of the comparison (module docstring): the responses per mode, each loop's integrator at every
    gain of ``gains`` (and past its top, by the grid's last step, while the top is either loop's best) on
    ``realisations`` realisations of ``frames`` (median residual over the pupil after ``settle_frames``), and the
    optical gains of the first ``n_gain_modes`` KL modes about ``probe_frames`` settled residuals of each best-gain
    loop, each sensor about its own loop's residuals and about the other's."""
    import time

    import torch

    from eofnn.control.baselines import Integrator
    from eofnn.interop.loop import MAX_EXTRA_GAINS, IntegratorControl, run_closed_loop
    from eofnn.interop.oopao_pyramid import gain_sensing_camera_gains, probe_optical_gains
    from eofnn.sim.sensing.optical_gains import OpticalGainProbe, kl_modes, optical_gains

    started = time.time()
    scenario = system.eofnn_scenario(frames)
    sensor = scenario.turbulence(seed, "test", realisations).operators.sensor
    sim = system.oopao(frames)
    progress(f"[{time.time() - started:.0f} s] built: eofnn keeps {sensor.kept_modes} of {sensor.grid.n_actuators} "
             f"modes, OOPAO {sim.n_seen} of {sim.n_actuators}")
    out = {"system": {**asdict(system),
                      "pupil_points": system.pupil_points, "eofnn_modulation_lambda_over_d": system.eofnn_modulation,
                      "modulation_points": int(sim.wfs.nTheta), "actuators": sim.n_actuators,
                      "kept_modes": {"eofnn": int(sensor.kept_modes), "oopao": int(sim.n_seen)}},
           "frames": frames, "settle_frames": settle_frames, "realisations": realisations, "seed": seed}
    out["response"] = response_ratios(sensor, sim, n_modes)
    out["response"]["ratio_with_oopaos_dm"] = response_with_oopaos_dm(sensor, sim, n_modes)
    seeds = [seed + r for r in range(realisations)]
    scan = {"eofnn": {}, "oopao": {}}

    def run(g: float) -> None:
        scan["eofnn"][g] = scenario.median_residual_nm(Integrator(g), frames, seed, "test", settle_frames,
                                                       realisations=realisations)
        medians = [run_closed_loop(sim, IntegratorControl(g), frames, s).metrics(settle_frames).median_rms_nm
                   for s in seeds]
        scan["oopao"][g] = None if None in medians else float(np.mean(medians))
        progress(f"[{time.time() - started:.0f} s] gain {g:g}: eofnn {scan['eofnn'][g]}, OOPAO {scan['oopao'][g]} nm")

    for g in gains:
        run(float(g))
    step = sorted(scan["eofnn"])[-1] - sorted(scan["eofnn"])[-2] if len(gains) > 1 else 0.1
    for _ in range(MAX_EXTRA_GAINS):  # climb past the grid's top while it is the best of either loop
        top = max(scan["eofnn"])
        if not any(values[top] is not None and values[top] == min(v for v in values.values() if v is not None)
                   for values in scan.values()):
            break
        run(round(top + step, 6))
    best = {}
    for code, values in scan.items():
        stable = {g: v for g, v in values.items() if v is not None}
        if not stable:
            raise ValueError(f"every integrator gain of {list(values)} diverged in {code}'s loop: give smaller gains")
        g = min(stable, key=stable.get)
        best[code] = {"gain": g, "median_rms_nm": stable[g]}
    out["integrator"] = {"scan": {code: {f"{g:g}": v for g, v in values.items()} for code, values in scan.items()},
                         "best": best, "fitting_error_nm": fitting_errors(scenario, sim, seeds, frames, settle_frames)}

    # Optical gains about each best-gain loop's settled residuals (the same frames in both).
    probe = OpticalGainProbe(sensor, settle_frames, frames, n_gain_modes, probe_frames)
    scenario.median_residual_nm(Integrator(best["eofnn"]["gain"]), frames, seed, "test", settle_frames,
                                realisations=realisations, on_chunk=probe)
    ours_own = probe.result()
    observer = _oopao_residuals(sim, probe.frames)
    for s in seeds:
        run_closed_loop(sim, IntegratorControl(best["oopao"]["gain"]), frames, s, observers=(observer,))
    theirs_maps = np.asarray(observer.maps)
    ours_maps = torch.cat(probe.residuals).numpy()  # (R x frames, n_pupil) on the same points as OOPAO's pupil
    full = np.zeros((len(ours_maps), sim.tel.resolution, sim.tel.resolution))
    full[:, sim.pupil_mask] = ours_maps
    modes = kl_modes(sensor.grid, probe.n_modes)
    order = actuator_order(np.asarray(sensor.grid.positions_m), sim.positions_m, sensor.grid.pitch_m)
    shapes = sensor.dm_surface(torch.as_tensor(modes.T))
    own_pupil = torch.as_tensor(theirs_maps[:, sim.pupil_mask])

    def rms(maps):
        inside = maps - maps.mean(-1, keepdims=True)
        return float(np.sqrt((inside ** 2).mean(-1)).mean())

    out["optical_gains"] = {
        "modes": probe.n_modes, "residuals": len(ours_maps), "frames": probe.frames,
        "residual_rms_nm": {"eofnn_loop": rms(ours_maps), "oopao_loop": rms(theirs_maps[:, sim.pupil_mask])},
        "eofnn_sensor_eofnn_loop": ours_own["gains"],
        "oopao_sensor_oopao_loop": probe_optical_gains(sim, modes[order], theirs_maps).mean(0).tolist(),
        "eofnn_sensor_oopao_loop": optical_gains(sensor, shapes, own_pupil).mean(0).tolist(),
        "oopao_sensor_eofnn_loop": probe_optical_gains(sim, modes[order], full).mean(0).tolist(),
        "oopao_gain_sensing_camera_oopao_loop": gain_sensing_camera_gains(sim, modes[order], theirs_maps).mean(0).tolist()}
    out["seconds"] = round(time.time() - started, 1)
    return out
