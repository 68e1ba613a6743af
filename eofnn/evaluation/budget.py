"""The error budget of a closed loop: fitting, aliasing, noise and temporal terms, from runs that isolate them.

Every term is a median of per-frame residual RMS (after settling) on the same test stream, split in quadrature
(as ``experiments/README.md`` section 6 does in OOPAO's loop):

- ``total``: the run itself;
- ``noise_free``: the same controller (built afresh), no sensor noise (photon, read and the plant's WFS noise);
- ``perfect``: no noise, and the sensor reads the turbulence the DM can fit (``P F phi``) in place of the
  reconstructed slopes ``R S phi``: no aliasing (a Shack-Hartmann scenario only). A predictor trained on aliased
  measurements meets unaliased ones there: its temporal term carries that shift. A pyramid scenario's perfect sensor
  reads ``P F phi`` of the residual linearly (:class:`~eofnn.sim.loop.pyramid.PyramidMeasurement`): its
  ``aliasing`` term holds the pyramid's nonlinearity too (its optical gains below 1 about the residual);
- ``fitting``: what no command can correct, the pupil's residual after the DM's least-squares fit on the modes the
  sensor sees (a Shack-Hartmann or pyramid scenario: the zonal loop scores the actuators, where there is none).

Then ``noise = sqrt(total² - noise_free²)``, ``aliasing = sqrt(noise_free² - perfect²)``,
``temporal = sqrt(perfect² - fitting²)``, ``fitting`` itself (the zonal sensor: ``temporal = noise_free``). A
difference that comes out negative (a controller that does better with noise, within the realisation's scatter) is
reported as 0 and the raw medians are kept beside the terms (``runs_nm``). The runs share the test stream's
turbulence, so the terms are differences on one realisation, not of independent ones.
"""

from __future__ import annotations

import math

from eofnn.lazy import lazy_module

torch = lazy_module("torch")


def quadrature_difference(a: float | None, b: float | None) -> float | None:
    """``sqrt(max(a² - b², 0))``; ``None`` when either is missing (a diverged run)."""
    if a is None or b is None:
        return None
    return math.sqrt(max(a * a - b * b, 0.0))


def fitting_nm(scenario, seed: int, stream: str, frames: int, settle_frames: int, realisations: int) -> float | None:
    """Median RMS over the pupil of the phase minus the DM's fit of it (``phi + IF u``, ``u = -P F phi``) on the frames
    after ``settle_frames``: the fitting error (``None`` for the zonal sensor)."""
    if not (scenario.sensor.is_shack_hartmann or scenario.sensor.is_pyramid):
        return None
    turbulence = scenario.turbulence(seed, stream, realisations)
    out = turbulence.products(settle_frames, frames)
    rms = turbulence.operators.pupil_rms(out["z"], out["sum"], out["sumsq"], -out["fit"])
    return float(rms.median())


def error_budget(total: float | None, noise_free: float | None, perfect: float | None,
                 fitting: float | None) -> dict:
    """The budget's terms (nm) from the runs' medians (module docstring)."""
    if fitting is None:  # the zonal sensor: no fine grid, no aliasing into a reconstruction
        return {"fitting_nm": None, "aliasing_nm": None, "noise_nm": quadrature_difference(total, noise_free),
                "temporal_nm": noise_free, "runs_nm": {"total": total, "noise_free": noise_free}}
    return {"fitting_nm": fitting, "aliasing_nm": quadrature_difference(noise_free, perfect),
            "noise_nm": quadrature_difference(total, noise_free), "temporal_nm": quadrature_difference(perfect, fitting),
            "runs_nm": {"total": total, "noise_free": noise_free, "perfect": perfect}}


def temporal_bound(median_rms_nm: float, budget: dict | None) -> float:
    """The largest gain in residual variance, fitting error removed, that removing a controller's temporal term alone
    would give: what a perfect predictor fed with the same aliased, noisy measurements could at best reach.

    Parameters
    ----------
    median_rms_nm : float
        The controller's median residual RMS over the pupil (nm).
    budget : dict or None
        Its :func:`error_budget` (``fitting_nm``, ``aliasing_nm``, ``noise_nm``; a missing term counts as 0).

    Returns
    -------
    float
        ``(median_rms² - fitting²) / (aliasing² + noise²)`` (the numerator at least 0; dimensionless): with the terms in
        quadrature, ``1 + temporal² / (aliasing² + noise²)``. ``inf`` when neither aliasing nor noise is left.
    """
    b = budget or {}
    fitting = b.get("fitting_nm") or 0.0
    rest = (b.get("aliasing_nm") or 0.0) ** 2 + (b.get("noise_nm") or 0.0) ** 2
    return max(median_rms_nm ** 2 - fitting ** 2, 0.0) / rest if rest > 0 else math.inf


def budget_runs(scenario, build_controller, evaluation, total: float | None, fitting: float | None) -> dict:
    """Run the isolating runs of one contender (``build_controller()`` makes it afresh) in ``scenario`` on
    ``evaluation``'s test stream, and return its :func:`error_budget`."""
    from eofnn.sim.loop.runner import run_loop

    ev = evaluation
    on_pupil = scenario.sensor.is_shack_hartmann or scenario.sensor.is_pyramid

    def median(isolate: str) -> float | None:
        plant = scenario.plant.with_errors(wfs_noise_nm=0.0)
        if on_pupil:
            turbulence = scenario.turbulence(ev.seed, "test", ev.realisations, isolate=isolate)
        else:
            turbulence = scenario.turbulence(ev.seed, "test", ev.realisations)
        result = run_loop(turbulence, plant, build_controller(), ev.frames, noise_seed=ev.seed, record=(),
                          divergence_factor=ev.divergence_factor, progress=False)
        if result.diverged:
            return None
        rms = result.residual_rms_nm if result.pupil_residual_rms_nm is None else result.pupil_residual_rms_nm
        return float(torch.quantile(rms[:, ev.settle_frames:].flatten(), 0.5))

    noise_free = median("noise_free")
    perfect = median("perfect") if on_pupil else None
    return error_budget(total, noise_free, perfect, fitting)


def budget_line(budget: dict) -> str:
    """``error budget: fitting 140.2, aliasing 61.0, noise 35.5, temporal 48.1 nm`` (terms that do not apply left out)."""
    terms = [f"{k[:-3]} {'diverged' if budget[k] is None else f'{budget[k]:.1f}'}"
             for k in ("fitting_nm", "aliasing_nm", "noise_nm", "temporal_nm")
             if budget[k] is not None or k in ("noise_nm", "temporal_nm")]
    return "error budget: " + ", ".join(terms) + " nm"
