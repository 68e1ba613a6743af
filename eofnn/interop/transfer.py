"""A predictor trained in eofnn's own Shack-Hartmann simulation of another simulator's system, run in that loop.

:mod:`eofnn.interop.antialias` trains its anti-aliasing EOF on the other simulator's truth. This module trains it
where eofnn's design says it should be trained, in eofnn's simulation, and carries it over:

1. :func:`train_in_eofnn`: the system of the OOPAO loop rebuilt in eofnn (:meth:`ShSystem.eofnn_scenario`: the
   actuators where OOPAO's are, at the same pitch; eofnn's Shack-Hartmann with OOPAO's detector, I band, photon
   noise at the same magnitude), the wind turned so that the turbulence moves the same way over the actuators in
   both (:data:`EOFNN_DIRECTION_OF_OOPAO`), and the 5 x 5 open-loop EOF fitted on eofnn's open-loop data with the
   DM's fit of the true phase as target (``data.target: dm_fit``), ridge alpha on validation frames;
2. :func:`transfer_filter`: its coefficients moved onto the other simulator's actuators by position. What eofnn's
   filter reads as POL values is the turbulence as its own sensor reports it, and what it commands is for a DM that
   applies what it is told; in the other loop the POL values are formed with the gain identified from that loop's
   telemetry (DM gain x the sensor's optical gain), so the coefficients are divided by it (commands for the
   DM's gain, reading through the sensor's). Actuators the other simulator has and eofnn's grid lacks (OOPAO's
   Fried DM reaches half a pitch past eofnn's pupil) hold their last POL value, a zero-order predictor.

Nothing of the other loop's telemetry enters the fit: only its identified gain scales the commands, as on a
telescope that deploys a filter trained in simulation. What differs (the reconstructor, the sensor's noise, its
optical gain, the turbulence's own generator) is what the transfer tests.
"""

from __future__ import annotations

import numpy as np

from eofnn.data.config import DataConfig
from eofnn.errors import ConfigError
from eofnn.interop.sh_system import ShSystem
from eofnn.models.linear import LinearFilter
from eofnn.runtime import PredictiveFilter
from eofnn.training.export import filter_coefficients, filter_taps
from eofnn.training.fit import fit_predictor
from eofnn.training.task import OptimizationConfig

#: eofnn's wind direction (degrees) whose turbulence moves over the actuators as OOPAO's at 0 degrees does (OOPAO's
#: 0 degrees carries it along the second coordinate of its DM's positions, eofnn's 0 along the first;
#: ``tests/test_interop_transfer.py`` measures it). Other OOPAO directions are not mapped.
EOFNN_DIRECTION_OF_OOPAO = {0.0: 90.0}


def eofnn_twin(sim) -> ShSystem:
    """The :class:`ShSystem` of an :class:`~eofnn.interop.oopao.OopaoLoop` (its size, sky, wind, rate and delay)."""
    s = sim.settings
    return ShSystem(n_subapertures=s["n_subapertures"], diameter_m=s["diameter_m"], r0_m=s["r0_m"],
                    outer_scale_m=s["outer_scale_m"], wind_speed_mps=s["wind_speed_mps"],
                    frame_rate_hz=s["frame_rate_hz"], delay_frames=s["delay_frames"],
                    samples_per_subaperture=s["pupil_pixels_per_subaperture"])


def eofnn_direction(oopao_direction_deg: float) -> float:
    """eofnn's wind direction for OOPAO's, or one line saying which directions are mapped."""
    direction = EOFNN_DIRECTION_OF_OOPAO.get(float(oopao_direction_deg))
    if direction is None:
        raise ConfigError(f"wind direction {oopao_direction_deg!r} deg is not mapped onto eofnn's: a predictor "
                          f"trained in eofnn is carried into OOPAO's loop at {sorted(EOFNN_DIRECTION_OF_OOPAO)} deg")
    return direction


def twin_scenario(sim, screen_frames: int, noise_nm: float | None = None):
    """eofnn's scenario of ``sim``'s system (module docstring, step 1); with ``noise_nm`` (the WFS noise per actuator
    identified from ``sim``'s telemetry) its guide star is moved until its own noise per actuator
    (:func:`eofnn.training.conditions.scenario_conditions`) is that: photon noise scales as ``10^(0.2 m)``."""
    from eofnn.sim.scenario import Scenario
    from eofnn.training.conditions import scenario_conditions

    magnitude = sim.settings["magnitude"] if sim.settings["photon_noise"] else None
    config = eofnn_twin(sim).eofnn_scenario(magnitude, screen_frames=screen_frames).to_dict()
    config["atmosphere"]["layers"][0]["wind_direction_deg"] = eofnn_direction(sim.settings["wind_direction_deg"])
    scenario = Scenario.from_dict(config)
    if magnitude is None or not noise_nm:
        return scenario
    own = scenario_conditions(scenario).wfs_noise_nm
    config["sensor"]["detector"]["magnitude"] = magnitude + 5 * np.log10(noise_nm / own)
    return Scenario.from_dict(config)


def train_in_eofnn(sim, *, frames: int = 6000, val_frames: int = 1200, history_length: int = 4,
                   radius: float = 2.5, seed: int = 0, noise_nm: float | None = None):
    """The anti-aliasing EOF trained in eofnn's simulation of ``sim``'s system (module docstring, step 1; with
    ``noise_nm``, its noise matched to the telemetry's, :func:`twin_scenario`): ``(fit result, scenario)``."""
    scenario = twin_scenario(sim, max(frames, val_frames) + 200, noise_nm)
    network = {"class_path": "eofnn.models.linear.LinearFilter",
               "init_args": {"structure": "neighbourhood", "radius": radius}}
    data = DataConfig(frames=frames, val_frames=val_frames, sequence_frames=max(frames, val_frames) + 200,
                      target="dm_fit", seed=seed)
    fitted = fit_predictor(scenario, "open_loop", history_length, network, data=data,
                           optimization=OptimizationConfig(alpha="auto"))
    return fitted, scenario


def transfer_filter(network: LinearFilter, spec, eofnn_positions_m, positions_m, dm_gain: float,
                    tolerance_m: float = 1e-6, static_gain: bool = False) -> tuple[PredictiveFilter, dict]:
    """eofnn's open-loop neighbourhood filter on another simulator's actuators (module docstring, step 2):
    ``(runtime filter, {"matched", "held"})``, the actuators matched by position within ``tolerance_m`` and those
    that hold their last POL value. ``static_gain``: the coefficients are scaled by one number so that the median
    actuator cancels a constant POL value exactly (its sum is ``-1 / dm_gain``), as a predictor of frozen flow must
    (scaled per actuator, the filters at the rim, whose sums are small, made the loop diverge)."""
    from scipy.spatial import cKDTree

    if spec.kind != "open_loop" or getattr(network, "structure", None) != "neighbourhood":
        raise ConfigError("only open-loop neighbourhood filters are carried between simulators (their taps read "
                          "POL values of actuators found by position)")
    coefficients, neighbours = filter_coefficients(network)  # (Ke, M, taps), (Ke, M) with -1 beyond the pupil
    ours, theirs = np.asarray(eofnn_positions_m, dtype=np.float64), np.asarray(positions_m, dtype=np.float64)
    distance, index = cKDTree(theirs).query(ours)
    if distance.max() > tolerance_m:
        raise ConfigError(f"eofnn's actuators are not on the simulator's: the farthest is {distance.max():.3g} m "
                          f"from any of them (tolerance {tolerance_m:g} m)")
    k, m, taps = len(theirs), neighbours.shape[1], coefficients.shape[-1]
    moved = np.zeros((k, m, taps))
    slots = np.full((k, m), -1, dtype=np.int64)
    if static_gain:  # one scale for the whole filter (per actuator, a rim filter's small sum would blow it up)
        coefficients = -coefficients / float(np.median(coefficients.sum(axis=(1, 2))))
    moved[index] = coefficients / dm_gain
    slots[index] = np.where(neighbours >= 0, index[np.clip(neighbours, 0, None)], -1)
    held = np.setdiff1d(np.arange(k), index)
    slots[held, 0] = held
    moved[held, 0, 0] = -1.0 / dm_gain  # tap 0 reads POL(n - d): hold it
    runtime = PredictiveFilter(moved, filter_taps(spec), spec.delay_frames, dm_gain, slots)
    return runtime, {"matched": int(len(index)), "held": int(len(held))}


def eofnn_trained(frames: int = 6000, val_frames: int = 1200, seed: int = 0, match_noise: bool = False,
                  static_gain: bool = False):
    """An ``external`` predictor of :func:`eofnn.interop.antialias.run_antialias`: trained in eofnn's simulation of
    the loop's system (:func:`train_in_eofnn`), carried onto its actuators with the gain identified from its
    recording (:func:`transfer_filter`); ``match_noise``: the simulation's guide star set so that its noise is the
    one identified from that recording; ``static_gain``: see :func:`transfer_filter`. Its info keeps the conditions
    it was trained in, so that the loop warns in one line where its own differ (:mod:`eofnn.interop.shift`)."""
    def build(sim, plant) -> tuple[PredictiveFilter, dict]:
        fitted, scenario = train_in_eofnn(sim, frames=frames, val_frames=val_frames, seed=seed,
                                          noise_nm=plant.wfs_noise_nm if match_noise else None)
        runtime, moved = transfer_filter(fitted.network, fitted.spec, scenario.grid.positions_m, sim.positions_m,
                                         plant.dm_gain, static_gain=static_gain)
        detector = scenario.sensor.detector
        # Carried over, it commands through the identified gain: that is the DM gain it now believes.
        conditions = {**(fitted.info.get("conditions") or {}), "dm_gain": float(plant.dm_gain),
                      "source": "eofnn's simulation of the system, carried with the identified gain"}
        return runtime, {"alpha": fitted.info.get("alpha"), "target": "dm_fit in eofnn's simulation",
                         "trained_magnitude": None if detector is None else detector.magnitude,
                         "val_loss": fitted.val_loss, **moved, "conditions": conditions}
    return build
