"""A predictor trained in eofnn's own Shack-Hartmann simulation of another simulator's system, run in that loop.

:mod:`eofnn.studies.antialias` trains its anti-aliasing EOF on the other simulator's truth. This module trains it
where eofnn's design says it should be trained, in eofnn's simulation, and carries it over:

1. :func:`train_in_eofnn`: the system of the OOPAO loop rebuilt in eofnn (:meth:`ShSystem.eofnn_scenario`: the
   actuators where OOPAO's are, at the same pitch; eofnn's Shack-Hartmann with OOPAO's detector, I band, photon
   noise), the wind turned so that the turbulence moves the same way over the actuators in both
   (:data:`EOFNN_DIRECTION_OF_OOPAO`), and the 5 x 5 open-loop EOF fitted on eofnn's open-loop data with the DM's
   fit of the true phase as target (``data.target: dm_fit``), ridge alpha on validation frames. By default the twin
   is made the loop's in two ways the loop's calibration and telemetry tell (never its truth): its guide star is
   set so that its noise per actuator is the one identified from the loop's telemetry, in eofnn's command units
   (OOPAO's command is ``sim.surface_per_command`` = 2.99 of eofnn's: its peak-1 influence functions overlap); and
   its inputs and targets are projected onto the command modes the loop's reconstructor sees
   (:func:`controlled_projector`);
2. :func:`transfer_filter`: its coefficients moved onto the other simulator's actuators by position. What eofnn's
   filter reads as POL values is the turbulence as its own sensor reports it, and what it commands is for a DM that
   applies what it is told; in the other loop the POL values are formed with the gain identified from that loop's
   telemetry (DM gain x the sensor's optical gain), so the coefficients are divided by it (commands for the
   DM's gain, reading through the sensor's). Actuators the other simulator has and eofnn's grid lacks (OOPAO's
   Fried DM reaches half a pitch past eofnn's pupil) hold their last POL value, a zero-order predictor.

Nothing of the other loop's telemetry enters the fit but two numbers: its identified gain scales the commands and
its identified noise sets the twin's guide star, as on a telescope that deploys a filter trained in simulation.
What differs (the reconstructor, the sensor's optical gain and aliasing, the turbulence's own generator) is what
the transfer tests.
"""

from __future__ import annotations

import numpy as np
import torch

from eofnn.data.config import DataConfig
from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.models.linear import LinearFilter
from eofnn.runtime import PredictiveFilter
from eofnn.studies.sh_system import ShSystem
from eofnn.training.export import filter_coefficients, filter_taps
from eofnn.training.task import OptimizationConfig
from eofnn.validation import Interval, check_value

#: eofnn's wind direction (degrees) whose turbulence moves over the actuators as OOPAO's at 0 degrees does (OOPAO's
#: 0 degrees carries it along the second coordinate of its DM's positions, eofnn's 0 along the first;
#: ``tests/test_interop_transfer.py`` measures it). The coordinates are swapped, so OOPAO's ``a`` is eofnn's
#: ``90 - a`` (:func:`eofnn_direction`; eofnn's identification finds it from OOPAO's telemetry, examples/twin_path.py).
EOFNN_DIRECTION_OF_OOPAO = {0.0: 90.0}


def eofnn_twin(sim, pupil: str = "grid") -> ShSystem:
    """The :class:`ShSystem` of an :class:`~eofnn.interop.oopao.OopaoLoop` (its size, sky, wind, rate and delay);
    ``pupil``: eofnn's grid's or OOPAO's (:class:`ShSystem`)."""
    s = sim.settings
    return ShSystem(n_subapertures=s["n_subapertures"], diameter_m=s["diameter_m"], r0_m=s["r0_m"],
                    outer_scale_m=s["outer_scale_m"], wind_speed_mps=s["wind_speed_mps"],
                    frame_rate_hz=s["frame_rate_hz"], delay_frames=s["delay_frames"],
                    samples_per_subaperture=s["pupil_pixels_per_subaperture"], pupil=pupil)


def eofnn_direction(oopao_direction_deg: float) -> float:
    """eofnn's wind direction for OOPAO's (``90 - a``, in [0, 360)), or one line naming a direction that is no
    number of degrees."""
    direction = float(oopao_direction_deg)
    if not np.isfinite(direction):
        raise ConfigError(f"wind direction {oopao_direction_deg!r} deg is not mapped onto eofnn's: a finite number of "
                          "degrees is")
    return EOFNN_DIRECTION_OF_OOPAO.get(direction, (90.0 - direction) % 360.0)


def twin_scenario(sim, screen_frames: int, noise_nm: float | None = None, pupil: str = "grid"):
    """eofnn's scenario of ``sim``'s system (module docstring, step 1); with ``noise_nm`` (a WFS noise per actuator in
    eofnn's command units: the one identified from ``sim``'s telemetry times ``sim.surface_per_command``) its guide
    star is moved until its own noise per actuator (:func:`eofnn.training.conditions.scenario_conditions`) is that:
    photon noise scales as ``10^(0.2 m)``."""
    from eofnn.sim.scenario import Scenario
    from eofnn.training.conditions import scenario_conditions

    magnitude = sim.settings["magnitude"] if sim.settings["photon_noise"] else None
    config = eofnn_twin(sim, pupil).eofnn_scenario(magnitude, screen_frames=screen_frames).to_dict()
    layers = sim.settings.get("layers") or [(1.0, sim.settings["wind_speed_mps"], sim.settings["wind_direction_deg"])]
    config["atmosphere"]["layers"] = [{**config["atmosphere"]["layers"][0], "cn2_fraction": float(fraction),
                                       "wind_speed_mps": float(speed), "wind_direction_deg": eofnn_direction(direction)}
                                      for fraction, speed, direction in layers]
    scenario = Scenario.from_dict(config)
    if magnitude is None or not noise_nm:
        return scenario
    own = scenario_conditions(scenario).wfs_noise_nm
    config["sensor"]["detector"]["magnitude"] = magnitude + 5 * np.log10(noise_nm / own)
    return Scenario.from_dict(config)


def controlled_projector(sim, eofnn_positions_m, keep: float = 0.5, modes=None, positions_m=None) -> torch.Tensor:
    """``(K_e, K_e)``: the projector onto the command modes ``sim``'s reconstructor sees (``sim.controlled_modes``, or
    ``modes`` ``(K, n)`` orthonormal on the actuators at ``positions_m``), on eofnn's actuators (those of ``sim``'s at
    the same positions): the modes restricted to them, orthonormalised, the directions they keep less than ``keep``
    of dropped (the rim actuators eofnn lacks carry the rest)."""
    modes = sim.controlled_modes if modes is None else modes
    index = match_positions(eofnn_positions_m, sim.positions_m if positions_m is None else positions_m)
    u, singular, _ = np.linalg.svd(np.asarray(modes, dtype=np.float64)[index], full_matrices=False)
    q = u[:, singular > keep]
    return torch.from_numpy(q @ q.T)


def train_in_eofnn(sim, *, frames: int = 6000, val_frames: int = 1200, history_length: int = 4,
                   radius: float = 2.5, seed: int = 0, noise_nm: float | None = None, controlled: bool = True,
                   sequences: int = 3, pupil: str = "grid"):
    """The anti-aliasing EOF trained in eofnn's simulation of ``sim``'s system (module docstring, step 1; with
    ``noise_nm``, in eofnn's command units, its noise matched, :func:`twin_scenario`; ``pupil``: the twin's, its grid's
    or OOPAO's, :class:`~eofnn.studies.sh_system.ShSystem`): ``(fit result, scenario)``.

    ``sequences`` open-loop sequences (independent realisations) of ``(frames + val_frames) / sequences`` frames, the
    last ``val_frames / sequences`` of each held out for the ridge alpha (the grid of
    :data:`eofnn.studies.study.ALPHA_PATH`, as the filters fitted in ``sim``'s own loop); inputs are eofnn's measured
    POL values, targets the DM's fit of the true phase. ``controlled``: both projected onto the command modes
    ``sim``'s reconstructor sees (:func:`controlled_projector`), the only ones its POL values hold and its DM is
    sent."""
    sequence = -(-(frames + val_frames) // sequences)
    scenario = twin_scenario(sim, sequence + 200, noise_nm, pupil)
    positions = np.asarray(scenario.grid.positions_m, dtype=np.float64)
    projector = controlled_projector(sim, positions) if controlled else None
    fitted = fit_in_twin(scenario, projector, sim.delay_frames, sim.frame_rate_hz, frames=frames,
                         val_frames=val_frames, history_length=history_length, radius=radius, seed=seed,
                         sequences=sequences)
    return fitted, scenario


def fit_in_twin(scenario, projector, delay_frames: int, frame_rate_hz: float, *, frames: int, val_frames: int,
                history_length: int = 4, radius: float = 2.5, seed: int = 0, sequences: int = 3):
    """The open-loop neighbourhood EOF fitted in ``scenario`` (a twin: its ``atmosphere.screen_frames`` at least
    ``(frames + val_frames) / sequences``) with the DM's fit of its true phase as target (:func:`train_in_eofnn`'s
    fit, whatever made the twin); ``projector`` ``(K, K)`` or ``None``: inputs and targets projected on it."""
    from eofnn.data.stream import SimulatedTelemetry
    from eofnn.studies.study import ALPHA_PATH
    from eofnn.telemetry.record import Telemetry
    from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry

    sequence = -(-(frames + val_frames) // sequences)
    spec = HistorySpec("open_loop", history_length, delay_frames)
    stream = SimulatedTelemetry(scenario, spec, sequences * sequence, stream="twin",
                                data=DataConfig(frames=sequences * sequence, sequence_frames=sequence, target="dm_fit",
                                                seed=seed))
    positions = torch.as_tensor(np.asarray(scenario.grid.positions_m, dtype=np.float64))
    recorded = []
    for i in range(stream.n_sequences):
        arrays = stream.telemetry(i)
        s, pol = arrays["s"][0], arrays["s_hat"][0]
        if projector is not None:
            s, pol = s @ projector, pol @ projector
        recorded.append(Telemetry(s=s, y=torch.zeros_like(pol), wfs=pol, delay_frames=delay_frames,
                                   positions_m=positions, frame_rate_hz=frame_rate_hz))
    network = {"class_path": "eofnn.models.linear.LinearFilter",
               "init_args": {"structure": "neighbourhood", "radius": radius}}
    return fit_from_telemetry(recorded, spec, network, plant={"dm_gain": 1.0},
                              data=TelemetryDataConfig(val_frames=-(-val_frames // sequences), target="s",
                                                       target_dm_gain=1.0, seed=seed),
                              optimization=OptimizationConfig(alpha="auto", alpha_path=ALPHA_PATH))


def match_positions(eofnn_positions_m, positions_m, tolerance_m: float = 1e-6) -> np.ndarray:
    """For each of eofnn's actuators, the index of the other simulator's at its position (within ``tolerance_m``),
    or one line naming the farthest."""
    from scipy.spatial import cKDTree

    distance, index = cKDTree(np.asarray(positions_m, dtype=np.float64)).query(
        np.asarray(eofnn_positions_m, dtype=np.float64))
    if distance.max() > tolerance_m:
        raise ConfigError(f"eofnn's actuators are not on the simulator's: the farthest is {distance.max():.3g} m "
                          f"from any of them (tolerance {tolerance_m:g} m)")
    return index


def transfer_filter(network: LinearFilter, spec, eofnn_positions_m, positions_m, dm_gain: float,
                    tolerance_m: float = 1e-6, static_gain: bool = False) -> tuple[PredictiveFilter, dict]:
    """eofnn's open-loop neighbourhood filter on another simulator's actuators (module docstring, step 2):
    ``(runtime filter, {"matched", "held"})``, the actuators matched by position within ``tolerance_m`` and those
    that hold their last POL value. ``static_gain``: the coefficients are scaled by one number so that the median
    actuator cancels a constant POL value exactly (its sum is ``-1 / dm_gain``), as a predictor of frozen flow must
    (scaled per actuator, the filters at the rim, whose sums are small, made the loop diverge)."""
    if spec.kind != "open_loop" or getattr(network, "structure", None) != "neighbourhood":
        raise ConfigError("only open-loop neighbourhood filters are carried between simulators (their taps read "
                          "POL values of actuators found by position)")
    coefficients, neighbours = filter_coefficients(network)  # (Ke, M, taps), (Ke, M) with -1 beyond the pupil
    index = match_positions(eofnn_positions_m, positions_m, tolerance_m)
    k, m, taps = len(positions_m), neighbours.shape[1], coefficients.shape[-1]
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


def eofnn_trained(frames: int = 6000, val_frames: int = 1200, seed: int = 0, match_noise: bool = True,
                  controlled: bool = True, static_gain: bool = False, sequences: int = 3, pupil: str = "grid"):
    """An ``external`` predictor of :func:`eofnn.studies.antialias.run_antialias`: trained in eofnn's simulation of
    the loop's system (:func:`train_in_eofnn`), carried onto its actuators with the gain identified from its
    recording (:func:`transfer_filter`).

    ``match_noise``: the simulation's guide star set so that its noise is the one identified from that recording,
    converted to eofnn's command units (``sim.surface_per_command``: OOPAO's commands are nm of influence-function
    peak, eofnn's nm of smooth surface, 2.99 times more); ``controlled``: trained in the command modes the loop's
    reconstructor sees; ``static_gain``: see :func:`transfer_filter`; ``pupil``: the twin's (its grid's, or OOPAO's
    with every one of its actuators and subapertures, :class:`~eofnn.studies.sh_system.ShSystem`). Its info keeps
    the conditions it was trained in, in the loop's command units, so that the loop warns in one line where its own
    differ (:mod:`eofnn.interop.shift`)."""
    def build(sim, plant) -> tuple[PredictiveFilter, dict]:
        units = float(getattr(sim, "surface_per_command", 1.0))  # eofnn's command units per one of the loop's
        fitted, scenario = train_in_eofnn(sim, frames=frames, val_frames=val_frames, seed=seed,
                                          noise_nm=plant.wfs_noise_nm * units if match_noise else None,
                                          controlled=controlled, sequences=sequences, pupil=pupil)
        runtime, moved = transfer_filter(fitted.network, fitted.spec, scenario.grid.positions_m, sim.positions_m,
                                         plant.dm_gain, static_gain=static_gain)
        from eofnn.training.conditions import scenario_conditions

        trained = scenario_conditions(scenario)
        noise = trained.wfs_noise_nm / units  # in the loop's command units
        detector = scenario.sensor.detector
        # Carried over, it commands through the identified gain: that is the DM gain it now believes.
        conditions = {**trained.to_dict(), "wfs_noise_nm": noise, "dm_gain": float(plant.dm_gain),
                      "source": "eofnn's simulation of the system (noise in the loop's command units), carried with "
                                "the identified gain"}
        return runtime, {"alpha": fitted.info.get("alpha"), "target": "dm_fit in eofnn's simulation",
                         "trained_magnitude": None if detector is None else detector.magnitude,
                         "trained_noise_nm": noise, "controlled_modes": controlled,
                         "twin_frames": frames + val_frames, "twin_sequences": sequences, "twin_pupil": pupil,
                         "val_loss": fitted.val_loss, **moved, "conditions": conditions}
    return build


def rim_actuators(positions_m, pitches: float) -> np.ndarray:
    """Boolean ``(K,)``: the actuators less than ``pitches`` actuator pitches inside the outermost one's radius (from
    the actuators' centroid), where a twin's pupil edge and the loop's differ most."""
    check_value("pitches", pitches, Interval(0, 100, unit="actuator pitches"))
    positions = np.asarray(positions_m, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 2 or len(positions) < 2:
        raise ConfigError(f"positions_m has shape {positions.shape}: expected (K, 2) with K >= 2 actuators")
    from scipy.spatial import cKDTree

    pitch = float(cKDTree(positions).query(positions, k=2)[0][:, 1].min())
    radius = np.hypot(*(positions - positions.mean(0)).T)
    return radius > radius.max() - pitches * pitch


def splice_filters(inner: PredictiveFilter, outer: PredictiveFilter, use_outer) -> PredictiveFilter:
    """One runtime filter that commands the actuators of ``use_outer`` (boolean ``(K,)``) as ``outer`` does and the
    others as ``inner``: both neighbourhood filters on the same actuators, with the same taps, delay and DM gain model
    (their neighbourhoods may differ in size). Each actuator's command depends on the shared histories only, so the
    spliced filter is exactly the two run side by side, and it exports like any other."""
    mask = np.asarray(use_outer, dtype=bool)
    for name, f in (("inner", inner), ("outer", outer)):
        if f.neighbours is None:
            raise ConfigError(f"{name} is not a neighbourhood filter: only neighbourhood filters are spliced")
    if (inner.n_actuators, inner.taps, inner.delay_frames, inner.dm_gain_model) != \
            (outer.n_actuators, outer.taps, outer.delay_frames, outer.dm_gain_model):
        raise ConfigError("inner and outer filters differ in actuators, taps, delay or DM gain model: only filters of "
                          "the same loop are spliced")
    if mask.shape != (inner.n_actuators,):
        raise ConfigError(f"use_outer has shape {mask.shape}: expected ({inner.n_actuators},), one flag per actuator")
    k, m = inner.n_actuators, max(inner.neighbours.shape[1], outer.neighbours.shape[1])

    def padded(f: PredictiveFilter) -> tuple[np.ndarray, np.ndarray]:
        extra = m - f.neighbours.shape[1]
        slots = np.pad(np.where(f.neighbours >= k, -1, f.neighbours), ((0, 0), (0, extra)), constant_values=-1)
        return np.pad(f.coefficients, ((0, 0), (0, extra), (0, 0))), slots

    (ci, ni), (co, no) = padded(inner), padded(outer)
    return PredictiveFilter(np.where(mask[:, None, None], co, ci), inner.taps, inner.delay_frames,
                            inner.dm_gain_model, np.where(mask[:, None], no, ni))
