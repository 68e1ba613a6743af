"""A predictor trained in a twin identified from another simulator's telemetry alone, run in that simulator's loop.

:func:`eofnn.studies.transfer.eofnn_trained` builds its twin from the simulator's settings (r0, L0, the wind, one
layer): knowledge a telescope does not have. :func:`identified_trained` builds it as a telescope would:

1. :func:`record_loop`: the loop's own dithered integrator recorded through :class:`RtcView` (what a real-time
   computer has: the commands ``y``, ``wfs = R @ slopes``, the actuator positions, the delay, the frame rate; its
   interaction matrix and reconstructor). The simulator's settings, truth (``s``) and description are never read;
2. :func:`identify_from_record`: eofnn's identification of the twin (:func:`eofnn.training.twin.identify_twin`, the
   code of ``eofnn twin``, with the command unit ``peak``: the record is in nm of influence-function peak) and the
   twin's scenario (``twin.yaml``'s config: the guide star set so that the twin's noise per actuator is the one
   identified, :func:`eofnn.training.twin.twin_magnitude`);
3. the anti-aliasing EOF fitted in that twin (:func:`eofnn.studies.transfer.fit_in_twin`: open-loop POL values
   in, the DM's fit of the twin's true phase as target, both projected on the command modes the recorded
   reconstructor sees), carried onto the loop's actuators by position with the identified gain
   (:func:`eofnn.studies.transfer.transfer_filter`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from eofnn.validation import COUNT, Interval, check_value

#: Seeds of the twin path (stated before any run): the recorded realisation and its dither are offset from the
#: study's seed by these, past every seed :func:`eofnn.studies.antialias.run_antialias` scores, scans or records
#: (seed + 2, 3, 20..., 40..., 140...).
RECORD_SEED_OFFSET, DITHER_SEED_OFFSET = 500, 600


@dataclass(frozen=True)
class RtcView:
    """What a real-time computer sees of ``sim`` (a :class:`~eofnn.interop.loop.SimulatorAdapter`): it steps the loop
    and knows its actuators, delay, rate and calibration, and nothing of the simulator's settings or truth
    (``describe`` names the simulator only)."""

    sim: object

    name = "rtc"

    @property
    def n_actuators(self) -> int:
        return self.sim.n_actuators

    @property
    def delay_frames(self) -> int:
        return self.sim.delay_frames

    @property
    def frame_rate_hz(self) -> float:
        return self.sim.frame_rate_hz

    @property
    def positions_m(self) -> np.ndarray:
        return self.sim.positions_m

    def reset(self, seed: int) -> None:
        self.sim.reset(seed)

    def project(self, command_nm: np.ndarray) -> np.ndarray:
        return self.sim.project(command_nm)

    def advance(self, command_nm: np.ndarray):
        return self.sim.advance(command_nm)

    def describe(self) -> dict:
        return {"simulator": "the loop's real-time computer (settings not read)"}


def record_loop(sim, frames: int, seed: int, gain: float = 0.25, dither_nm: float = 10.0, settle_frames: int = 200):
    """The loop's dithered integrator (``gain``, ``dither_nm`` of white dither seeded ``seed`` +
    :data:`DITHER_SEED_OFFSET`) on the realisation ``seed`` + :data:`RECORD_SEED_OFFSET`, ``frames`` frames, the first
    ``settle_frames`` dropped: a :class:`~eofnn.telemetry.record.Telemetry` of ``y``, ``wfs``, positions, delay and
    rate only."""
    from eofnn.interop.loop import IntegratorControl, require_recorded, run_closed_loop
    from eofnn.telemetry.record import Telemetry

    check_value("frames", frames, COUNT)
    check_value("settle_frames", settle_frames, Interval(0, frames, closed="left", integer=True, unit="frames"))
    view = RtcView(sim)
    record = require_recorded(run_closed_loop(view, IntegratorControl(gain, dither_nm, seed=seed + DITHER_SEED_OFFSET),
                                              frames, seed + RECORD_SEED_OFFSET), gain, view)
    return Telemetry(y=torch.from_numpy(record.y[settle_frames:]), wfs=torch.from_numpy(record.wfs[settle_frames:]),
                     delay_frames=record.delay_frames, frame_rate_hz=record.frame_rate_hz,
                     positions_m=torch.from_numpy(record.positions_m))


def identify_from_record(telemetry, interaction_matrix, reconstructor, screen_frames: int, seed: int = 0,
                         command_unit: str = "peak"):
    """``(identification, scenario config)``: the twin of the loop that recorded ``telemetry`` from the record and
    its two matrices alone, as ``eofnn twin`` identifies it and writes ``twin.yaml`` (a Shack-Hartmann twin's guide
    star set to the identified noise)."""
    from eofnn.training.twin import identify_twin

    found = identify_twin(telemetry, interaction_matrix=interaction_matrix, reconstructor=reconstructor,
                          command_unit=command_unit, seed=seed)
    return found, found.twin_config(screen_frames)


def seen_modes(reconstructor, relative: float = 1e-8) -> np.ndarray:
    """``(K, n)``: an orthonormal basis of the commands a reconstructor ``(K, S)`` can give (its column space)."""
    u, singular, _ = np.linalg.svd(np.asarray(reconstructor, dtype=np.float64), full_matrices=False)
    return u[:, singular > relative * singular[0]]


def identified_trained(record_frames: int = 4000, frames: int = 6000, val_frames: int = 1200, sequences: int = 3,
                       seed: int = 0, out=None):
    """An ``external`` predictor of :func:`eofnn.studies.antialias.run_antialias` trained in a twin identified from
    the loop's own telemetry (module docstring): ``record_frames`` recorded (seed ``seed`` + the offsets), the twin
    fitted on ``frames + val_frames`` of its frames in ``sequences`` realisations (seed ``seed``). ``out``: a folder
    that receives ``twin.yaml`` and ``identified.json``. Only ``sim``'s stepping, actuators, delay, rate,
    interaction matrix and reconstructor are read."""
    def build(sim, plant) -> tuple:
        import yaml

        from eofnn.sim.scenario import Scenario
        from eofnn.studies.transfer import controlled_projector, fit_in_twin, transfer_filter
        from eofnn.training.conditions import scenario_conditions

        telemetry = record_loop(sim, record_frames, seed)
        sequence = -(-(frames + val_frames) // sequences)
        found, config = identify_from_record(telemetry, sim.interaction_matrix, sim.reconstructor, sequence + 200,
                                             seed=seed)
        if out is not None:
            from pathlib import Path

            Path(out).mkdir(parents=True, exist_ok=True)
            (Path(out) / "twin.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
            found.to_json(Path(out) / "identified.json")
        gain = float(found.value("dm_gain"))
        config = {**config, "plant": {**config["plant"], "dm_gain": 1.0}}  # trained open loop; carried with `gain`
        scenario = Scenario.from_dict(config)
        positions = np.asarray(scenario.grid.positions_m, dtype=np.float64)
        projector = controlled_projector(sim, positions, modes=seen_modes(sim.reconstructor),
                                         positions_m=sim.positions_m)
        fitted = fit_in_twin(scenario, projector, sim.delay_frames, sim.frame_rate_hz, frames=frames,
                             val_frames=val_frames, seed=seed, sequences=sequences)
        runtime, moved = transfer_filter(fitted.network, fitted.spec, positions, sim.positions_m, gain)
        units = _peak_scale(found)  # eofnn's command units per one of the loop's
        trained = scenario_conditions(scenario)
        conditions = {**trained.to_dict(), "wfs_noise_nm": trained.wfs_noise_nm / units, "dm_gain": gain,
                      "source": "a twin identified from the loop's telemetry alone (noise in the loop's command "
                                "units), carried with the identified gain"}
        layers = [{k: round(float(lay[k]), 3) for k in ("speed_mps", "direction_deg", "weight")}
                  for lay in found.layers]
        return runtime, {"alpha": fitted.info.get("alpha"), "target": "dm_fit in the identified twin",
                         "knowledge": "the loop's telemetry (y, wfs, positions, delay, rate), interaction matrix and "
                                      "reconstructor: no simulator setting or truth",
                         "identified": {"r0_m": found.value("r0_m"), "outer_scale_m": found.value("outer_scale_m"),
                                        "wfs_noise_nm_eofnn_units": found.value("wfs_noise_nm"), "dm_gain": gain,
                                        "layers": layers},
                         "record_frames": record_frames, "record_seed": seed + RECORD_SEED_OFFSET,
                         "twin_frames": frames + val_frames, "twin_sequences": sequences, "twin_seed": seed,
                         "val_loss": fitted.val_loss, **moved, "conditions": conditions}
    return build


def _peak_scale(found) -> float:
    """eofnn's command units per one of the record's (the identification's ``peak`` scale)."""
    from eofnn.sim.sensing.least_squares import surface_per_command

    return surface_per_command(found.mechanical_coupling)


def gap_closed(metrics: dict, name: str, truth: str = "eof_antialias") -> dict:
    """The share of the gap between the best classical controller and ``truth`` (the same filter trained on the
    simulator's truth) that ``name`` closes, in plain variance over the scored realisations (the mean of the squared
    median RMS): ``(best - name) / (best - truth)``, with the best classical controller chosen on the scan realisation
    (``on_scan``) and on the scored ones (``on_scored``). ``None``, with the reason in ``why``, where a contender
    diverged or is absent, or where ``truth`` does not beat the best classical controller (no gap to close)."""
    results = metrics["contenders"]

    def variance(contender: str):
        rms = results.get(contender, {}).get("realisations_median_rms_nm")
        return None if not rms or None in rms else float(np.mean(np.square(rms)))

    out = {"predictor": name, "truth": truth, "variance_nm2": {}}
    for key, best in (("on_scan", metrics.get("best_classical")), ("on_scored", metrics.get("best_classical_on_scored"))):
        values = [variance(best), variance(name), variance(truth)] if best else [None]
        share, why = None, ""
        if None in values:
            why = "a contender diverged or is absent"
        elif values[2] >= values[0]:
            why = f"{truth} does not beat {best}: there is no gap to close"
        else:
            share = (values[0] - values[1]) / (values[0] - values[2])
        out[key] = {"best_classical": best, "share": share, **({"why": why} if why else {})}
        if best:
            out["variance_nm2"][best] = values[0]
    out["variance_nm2"].update({name: variance(name), truth: variance(truth)})
    return out
