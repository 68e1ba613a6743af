"""eofnn's Shack-Hartmann loop against OOPAO's, on one system: eofnn's sensor against an independent simulator's.

:func:`compare` builds the system of an :class:`~eofnn.studies.sh_system.ShSystem` in both simulators (how they
line up: :mod:`eofnn.studies.sh_system`) and measures, per guide-star magnitude, in each: the best-gain integrator's
median residual over the pupil (gains scanned on a realisation of their own), and its error budget on
``realisations`` others (fitting, aliasing, noise, temporal: :mod:`eofnn.evaluation.budget`'s split). Beside them,
what tells the two sensors apart (:mod:`eofnn.studies.sh_diagnostics`): OOPAO's slope noise against eofnn's formula,
the noise each reconstructor puts on the pupil, OOPAO's optical gain in the loop, its geometric SH's aliasing,
OOPAO's sensor on eofnn's turbulence, eofnn's residual over OOPAO's (smaller) pupil, and both turbulences'
structure functions against von Karman's. ``experiments/sh_vs_oopao.py`` runs it and writes the table.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from eofnn.errors import require
from eofnn.interop.loop import scan_integrator
from eofnn.studies.sh_system import (
    ShSystem,
    budget_terms,
    eofnn_gain_scan,
    eofnn_runs,
    oopao_fitting,
    oopao_medians,
)
from eofnn.validation import COUNT, Constraint, Interval, check_value, validated


@dataclass(frozen=True)
@validated
class CompareConfig:
    """Frames, seeds and gains of :func:`compare`: each realisation runs ``frames`` frames, scored after
    ``settle_frames``; the gains are scanned on a realisation of their own in each simulator, per magnitude."""

    magnitudes: tuple[float, ...] = (8.0, 10.0)
    frames: int = 1000
    settle_frames: int = 200
    realisations: int = 3
    gains: tuple[float, ...] = (0.3, 0.4, 0.5, 0.6)
    seed: int = 1
    eofnn_turbulence: bool = True
    geometric: bool = True

    _constraints: ClassVar[dict[str, Constraint]] = {
        "frames": COUNT, "realisations": COUNT, "seed": Interval(0, 2 ** 31 - 1000, integer=True),
        "settle_frames": Interval(0, None, integer=True, unit="frames"),
    }

    def __post_init__(self) -> None:
        require(self.settle_frames < self.frames,
                f"settle_frames={self.settle_frames} is invalid: it must be below frames={self.frames}")
        require(len(self.gains) >= 2 and len(self.magnitudes) >= 1,
                f"gains={self.gains!r} and magnitudes={self.magnitudes!r} are invalid: give at least two gains and "
                "one magnitude")
        for g in self.gains:
            check_value("gains", g, Interval(0, 2, closed="neither"))


def mapping(system: ShSystem, scenario, sim) -> dict:
    """How the two systems line up: pupils, actuators, subapertures, controlled modes."""
    from eofnn.sim.loop.sensing import loop_operators

    sensor = loop_operators(scenario.grid, scenario.sensor.shack_hartmann()).sensor
    return {"pitch_m": system.pitch_m,
            "oopao": {"pupil_m": system.diameter_m, "actuators": sim.n_actuators, "seen_modes": sim.n_seen,
                      "subapertures": int(np.asarray(sim.wfs.valid_subapertures).sum()),
                      "rcond": sim.settings["rcond"], "sh_pixels": sim.n_pixels_per_subaperture},
            "eofnn": {"pupil_m": scenario.grid.diameter_m, "grid_n_across": scenario.grid.n_across,
                      "actuators": scenario.grid.n_actuators, "seen_modes": sensor.kept_modes,
                      "subapertures": sensor.geometry.n_subapertures, "relative_cut": sensor.relative_cut}}


def compare(system: ShSystem, config: CompareConfig | None = None, log=None) -> dict:
    """Everything the comparison reports (``experiments/sh_vs_oopao.py`` writes it): per magnitude, in each
    simulator, the best-gain integrator (scanned on a realisation of its own) and its error budget on
    ``realisations`` others; OOPAO's slope noise, optical gain and geometric SH; the turbulences' structure."""
    from eofnn.interop.oopao import measure_sensor_gain
    from eofnn.studies.sh_diagnostics import (
        eofnn_fit_over_disc,
        eofnn_noise_propagation,
        oopao_noise_propagation,
        oopao_slope_noise,
        oopao_slope_units,
        structure_functions,
    )

    c, log = config or CompareConfig(), log or (lambda message: None)
    seeds, scan_seed = [c.seed + i for i in range(c.realisations)], c.seed + 1000
    sims, runs = {}, {}

    def sim(sensor: str, magnitude=None, turbulence="oopao"):
        key = (sensor, magnitude, turbulence)
        if key not in sims:
            log(f"building OOPAO: {sensor}, magnitude {magnitude}, {turbulence} turbulence")
            sims[key] = system.oopao(sensor, 8.0 if magnitude is None else magnitude, magnitude is not None,
                                     turbulence, c.frames)
        return sims[key]

    def medians(gain: float, sensor: str, magnitude=None, turbulence="oopao") -> list:
        key = (gain, sensor, magnitude, turbulence)
        if key not in runs:
            log(f"OOPAO loop: gain {gain}, {sensor}, magnitude {magnitude}, {turbulence} turbulence")
            runs[key] = oopao_medians(sim(sensor, magnitude, turbulence), gain, seeds, c.frames, c.settle_frames)
        return runs[key]

    log("OOPAO fitting error")
    fitting = {t: oopao_fitting(sim("perfect", None, t), seeds, c.frames, c.settle_frames)
               for t in (("oopao", "eofnn") if c.eofnn_turbulence else ("oopao",))}
    units = oopao_slope_units(sim("shack_hartmann"))
    out = {"system": _fields(system), "config": _fields(c), "seeds": {"scored": seeds, "scan": scan_seed},
           "mapping": mapping(system, system.eofnn_scenario(None, c.frames), sim("perfect")),
           "noise_propagation": {"eofnn": eofnn_noise_propagation(system.eofnn_scenario(None, c.frames)),
                                 "oopao": oopao_noise_propagation(sim("shack_hartmann"), units)},
           "magnitudes": {}}
    for magnitude in c.magnitudes:
        log(f"eofnn: magnitude {magnitude}")
        scenario = system.eofnn_scenario(magnitude, c.frames)
        scan = eofnn_gain_scan(scenario, c.gains, c.seed, c.frames, c.settle_frames)
        e_runs = eofnn_runs(scenario, scan["gain"], c.seed, c.realisations, c.frames, c.settle_frames,
                            inner_diameter_m=system.diameter_m)
        detector = scenario.sensor.detector
        eofnn = {"gain": scan["gain"], "scan": scan["scan"], "runs": e_runs,
                 "terms": budget_terms(e_runs["none"], e_runs["noise_free"], e_runs["perfect"], e_runs["fitting"]),
                 "inner_terms": budget_terms(*(e_runs[f"inner:{k}"] for k in ("none", "noise_free", "perfect",
                                                                              "fitting"))),
                 "slope_noise_nm": scenario.sensor.slope_noise_nm(system.pitch_m, 1 / system.frame_rate_hz),
                 "photons_per_subaperture": detector.photons_per_subaperture(system.pitch_m,
                                                                             1 / system.frame_rate_hz),
                 "fit_over_oopao_pupil": eofnn_fit_over_disc(scenario, c.seed, c.realisations, c.frames,
                                                             c.settle_frames, system.diameter_m)}
        log(f"OOPAO: magnitude {magnitude}, gain scan")
        o_scan = scan_integrator(sim("shack_hartmann", magnitude), c.gains, c.frames, scan_seed, c.settle_frames)
        g = o_scan["gain"]
        o_runs = {"none": medians(g, "shack_hartmann", magnitude), "noise_free": medians(g, "shack_hartmann"),
                  "perfect": medians(g, "perfect"), "fitting": fitting["oopao"]}
        log(f"OOPAO: magnitude {magnitude}, slope noise and optical gain")
        oopao = {"gain": g, "scan": o_scan["scan"], "runs": o_runs,
                 "terms": budget_terms(o_runs["none"], o_runs["noise_free"], o_runs["perfect"], o_runs["fitting"]),
                 "slope_noise": oopao_slope_noise(sim("shack_hartmann", magnitude), g, min(c.frames, 400), scan_seed),
                 "optical_gain": measure_sensor_gain(sim("shack_hartmann", magnitude), g, min(c.frames, 400),
                                                     scan_seed)}
        if c.geometric:
            o_runs["geometric"] = medians(g, "geometric")
            oopao["geometric_aliasing"] = [_quadrature(a, b) for a, b in
                                           zip(o_runs["geometric"], o_runs["perfect"], strict=True)]
        # eofnn with OOPAO's noise: its white slope noise scaled (by widening the spot) until what its reconstructor
        # puts on the pupil equals what OOPAO's puts there in the loop
        eofnn["open_loop_pupil_nm"] = eofnn["slope_noise_nm"] * out["noise_propagation"]["eofnn"]
        widen = oopao["slope_noise"]["loop_pupil_nm"] / eofnn["open_loop_pupil_nm"]
        matched = eofnn_runs(system.eofnn_scenario(magnitude, c.frames, widen), eofnn["gain"], c.seed,
                             c.realisations, c.frames, c.settle_frames, isolates=("none",))
        eofnn["matched_noise"] = {"spot_fwhm_lambda_over_d": widen, "none": matched["none"],
                                  "noise": [_quadrature(a, b) for a, b in
                                            zip(matched["none"], e_runs["noise_free"], strict=True)]}
        entry = {"eofnn": eofnn, "oopao": oopao}
        if c.eofnn_turbulence:
            t_runs = {"none": medians(g, "shack_hartmann", magnitude, "eofnn"),
                      "noise_free": medians(g, "shack_hartmann", None, "eofnn"),
                      "perfect": medians(g, "perfect", None, "eofnn"), "fitting": fitting["eofnn"]}
            entry["oopao_on_eofnn_turbulence"] = {
                "gain": g, "runs": t_runs,
                "terms": budget_terms(t_runs["none"], t_runs["noise_free"], t_runs["perfect"], t_runs["fitting"])}
        out["magnitudes"][str(magnitude)] = entry
    log("structure functions")
    out["structure_function"] = structure_functions(system, seeds, c.frames)
    return out


def _quadrature(a, b):
    from eofnn.evaluation.budget import quadrature_difference

    return quadrature_difference(a, b)


def _fields(obj) -> dict:
    from dataclasses import asdict

    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(obj).items()}
