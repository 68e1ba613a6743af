"""A twin of the user's system identified from its closed-loop telemetry alone (``eofnn twin``).

What a real loop records: the commands ``y``, the measurements ``wfs`` (or slopes with an interaction matrix or a
reconstructor), the dither if one was added, the actuator positions, the delay and the frame rate. Nothing here reads
the simulator's truth (``s``, ``eps``) or its configuration; every quantity comes with an uncertainty and the method
that gave it, and a quantity the record cannot tell is given with a one-line warning and the value assumed.

1. *The pupil* (:func:`~eofnn.training.twin_pupil.pupil_from_matrices`): the actuators are the columns of ``y`` at
   their positions; an interaction matrix says which of them move the slopes (a column of almost zero is an actuator
   outside the lit pupil: refused, since the telemetry controls it) and which slopes respond (the valid
   subapertures); a reconstructor must be ``(K, S)``.
2. *The plant*: the DM gain times the optical gain and the WFS lag by :func:`eofnn.training.identify.identify_plant`
   when the record holds a dither; without one it is not identifiable and 1 is assumed. The delay is the file's.
3. *The pseudo-open-loop signal* ``s_hat(n) = wfs(n) - g y(n)`` (eofnn's alignment, ``docs/telemetry.md``: ``wfs(n)``
   measures ``s(n) + g y(n)``; a fractional delay ``d + f`` averages the commands, ``(1 - f) y(n) + f y(n - 1)``).
4. *The WFS noise* (:func:`~eofnn.training.twin_seeing.noise_floor`): the floor ``C_v`` of ``s_hat``'s temporal
   cross-periodogram at 0.25-0.5 cycles per frame beside an ``f^(-11/3)`` tail, less the share of the twin's own
   turbulence floor (an aliased Shack-Hartmann's) the record shows; ``sigma^2 R R^T`` fitted with a reconstructor.
5. *r0 and L0* (:func:`~eofnn.training.twin_seeing.seeing_and_noise`,
   :func:`~eofnn.training.twin_seeing.fit_seeing`): the noise-corrected covariance of ``s_hat`` against the
   covariance of the twin's own noise-free turbulence (:func:`~eofnn.training.twin_seeing.reference_covariances`: the
   twin's grid, sensor and identified winds, simulated at r0 = :data:`~eofnn.training.twin_seeing.R0_REFERENCE_M` for
   each L0 of :data:`~eofnn.training.twin_seeing.OUTER_SCALES_M`), so that the sensing (a subaperture average, or a
   Shack-Hartmann's reconstruction with its aliasing, in command units) is the twin's: their structure functions over
   actuator separations from 1.5 pitches to half the pupil, piston, tip and tilt projected out of both, differ by the
   factor ``(r0 / r0_ref)^(-5/3)`` (r0 at :data:`~eofnn.training.twin_seeing.R0_WAVELENGTH_M`); L0 is the one whose
   shape fits best (not identifiable on a pupil much smaller than L0: one line says so and the twin keeps the best
   fit). A Shack-Hartmann's aliased turbulence is not smooth over two frames and leaves part of itself in the noise
   estimate of 4; the references say how much per unit of their turbulence, so the noise and r0 are solved for
   together.
6. *The layers* (:func:`~eofnn.training.twin_layers.identify_layers`): :func:`eofnn.control.wind.identify_winds`
   (lagged cross-spectra of the whitened POL maps: a frozen-flow layer's peak moves by ``v tau``) fitted with 1 to
   ``max_layers`` layers, the count chosen by the record's own consistency: a layer is added only if every block of
   the record finds it again with the same wind, and it carries a fair share of the turbulence (an aliased
   Shack-Hartmann's modes have an apparent motion that a cross-spectrum fit takes for a weak extra layer, whose wind
   changes from block to block); layers closer than :data:`~eofnn.training.twin_layers.MERGE_SPEED_MPS` are merged,
   and the winds' spread over the blocks gives the uncertainty. A Bayesian information criterion on the
   cross-spectra's residual is reported beside it, not used: the cross-spectra's values are not independent, and it
   takes the aliased component for a layer.

Uncertainties are standard errors from splitting the record into ``blocks`` consecutive blocks (the spread of the
blocks' estimates over ``sqrt(blocks)``), except the plant's (the regression's own standard errors).
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eofnn.errors import TelemetryError
from eofnn.lazy import lazy_module
from eofnn.telemetry.units import OPTICAL_GAIN, PEAK, check_units, conversion
from eofnn.training.twin_layers import MERGE_SPEED_MPS, MIN_EXTRA_WEIGHT, Lattice, identify_layers, record_blocks, standard_error
from eofnn.training.twin_pupil import pupil_from_matrices
from eofnn.training.twin_seeing import (
    OUTER_SCALES_M,
    R0_REFERENCE_M,
    R0_WAVELENGTH_M,
    REFERENCE_FRAMES,
    pseudo_open_loop,
    ptt_projector,
    reference_covariances,
    seeing_and_noise,
)
from eofnn.validation import check_value

torch = lazy_module("torch")

#: The DM's influence functions when the record has slopes and no coupling is given: Gaussian, this value one pitch
#: away (OOPAO's and eofnn's default).
DEFAULT_COUPLING = 0.35
#: Fewest frames from which a layer is identified.
MIN_LAYER_FRAMES = 1000


@dataclass
class Estimate:
    """One identified quantity: its value, standard error (None where there is none), unit and method."""

    value: object
    uncertainty: object
    unit: str
    method: str
    warning: str = ""

    def to_dict(self) -> dict:
        out = {"value": self.value, "uncertainty": self.uncertainty, "unit": self.unit, "method": self.method}
        if self.warning:
            out["warning"] = self.warning
        return out


@dataclass
class TwinIdentification:
    """What :func:`identify_twin` found: named :class:`Estimate` s, the layers, the twin's geometry, warnings."""

    estimates: dict[str, Estimate] = field(default_factory=dict)
    layers: list[dict] = field(default_factory=list)
    grid: dict = field(default_factory=dict)
    frame_rate_hz: float = 1000.0
    sensor: str = "subaperture"
    remove_ptt: bool = True
    mechanical_coupling: float = DEFAULT_COUPLING
    lit_pupil_m: float | None = None
    warnings: list[str] = field(default_factory=list)

    def value(self, name: str):
        return self.estimates[name].value

    @property
    def optical_gain(self) -> float:
        """The sensor's optical gain the user gave (1 where none was: the twin's DM gain is then the product)."""
        given = self.estimates.get("optical_gain")
        return 1.0 if given is None else float(given.value)

    def warn(self, message: str) -> None:
        self.warnings.append(message)

    def to_dict(self) -> dict:
        return {"quantities": {k: e.to_dict() for k, e in self.estimates.items()}, "layers": self.layers,
                "grid": self.grid, "frame_rate_hz": self.frame_rate_hz, "sensor": self.sensor,
                "remove_ptt": self.remove_ptt, "warnings": self.warnings}

    def to_json(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n")

    def scenario_config(self, screen_frames: int = 10000, noise_magnitude: float | None = None,
                        r0_m: float | None = None, outer_scale_m: float | None = None) -> dict:
        """The twin as an eofnn scenario config (the fields of :class:`~eofnn.sim.scenario.Scenario`); a Shack-Hartmann
        twin's guide star is ``noise_magnitude`` (R band: :func:`twin_magnitude`); ``r0_m`` and ``outer_scale_m``
        replace the identified ones."""
        r0_m = self.value("r0_m") if r0_m is None else r0_m
        outer_scale_m = self.value("outer_scale_m") if outer_scale_m is None else outer_scale_m
        layers = [{"cn2_fraction": round(lay["weight"], 4), "wind_speed_mps": round(lay["speed_mps"], 3),
                   "wind_direction_deg": round(lay["direction_deg"], 2)} for lay in self.layers]
        config = {
            "grid": self.grid,
            "atmosphere": {"r0_m": round(float(r0_m), 5), "r0_wavelength_m": R0_WAVELENGTH_M,
                           "outer_scale_m": float(outer_scale_m), "layers": layers, "model": "exact",
                           "screen_frames": int(screen_frames), "remove_ptt": self.remove_ptt},
            "frame_rate_hz": float(self.frame_rate_hz),
            "plant": {"delay_frames": self.value("delay_frames"),
                      "dm_gain": round(float(self.value("dm_gain")) / self.optical_gain, 4)},
        }
        if self.sensor == "shack_hartmann":
            config["sensor"] = {"kind": "shack_hartmann", "mechanical_coupling": self.mechanical_coupling,
                                "detector": {"band": "R", "magnitude": round(float(noise_magnitude), 3)}}
            if self.lit_pupil_m is not None:
                config["sensor"]["pupil_diameter_m"] = self.lit_pupil_m
        else:
            noise = self.estimates.get("wfs_noise_nm")  # not yet identified while r0 is being fitted
            config["plant"]["wfs_noise_nm"] = 0.0 if noise is None else round(float(noise.value), 4)
        return config

    def twin_config(self, screen_frames: int = 10000) -> dict:
        """``twin.yaml``: :meth:`scenario_config`, a Shack-Hartmann twin's guide star giving the noise identified."""
        noise = self.value("wfs_noise_nm") if self.sensor == "shack_hartmann" else None
        if noise is not None and not noise > 0:
            raise TelemetryError(f"the WFS noise per actuator is identified as {noise:g} nm (the aliasing correction "
                                 "took all of the noise estimate): a Shack-Hartmann twin's guide star cannot be set for it")
        magnitude = None if noise is None else twin_magnitude(self.scenario_config(screen_frames, 8.0), noise)
        return self.scenario_config(screen_frames, noise_magnitude=magnitude)


def twin_magnitude(config: dict, noise_nm: float, start: float = 8.0) -> float:
    """The R magnitude of a Shack-Hartmann twin's guide star whose photon noise per actuator is ``noise_nm``
    (:func:`eofnn.training.conditions.scenario_conditions`: photon noise scales as ``10^(0.2 m)``)."""
    from eofnn.sim.scenario import Scenario
    from eofnn.training.conditions import scenario_conditions

    cfg = json.loads(json.dumps(config))
    cfg["sensor"]["detector"]["magnitude"] = start
    own = scenario_conditions(Scenario.from_dict(cfg)).wfs_noise_nm
    return start + 5 * math.log10(noise_nm / own)


# ----------------------------------------------------------------------------------------------------------- whole

def identify_twin(telemetry, *, interaction_matrix=None, reconstructor=None, max_layers: int = 3,
                  max_speed_mps: float = 40.0, blocks: int = 4, mechanical_coupling: float | None = None,
                  command_unit="surface", measurement_unit=None, optical_gain: float | str | None = None,
                  seed: int = 0) -> TwinIdentification:
    """Identify the twin of the system that recorded ``telemetry`` (a :class:`~eofnn.telemetry.record.Telemetry`
    with ``y``, ``wfs``, ``positions_m``, the delay and the frame rate; ``s``, ``eps`` and ``config`` are never read)
    (module docstring). ``interaction_matrix`` ``(S, K)`` and ``reconstructor`` ``(K, S)`` replace the file's;
    ``mechanical_coupling``: the DM's Gaussian influence functions' value one pitch away (a record of slopes without
    it assumes :data:`DEFAULT_COUPLING`, in one line); ``command_unit``: what one unit of ``y`` is
    (:mod:`eofnn.telemetry.units`), e.g. ``"surface"`` (nm of smooth DM surface, eofnn's) or ``"peak"`` (nm at the
    peak of one actuator's influence function, OOPAO's and many RTCs': multiplied by the lattice sum of the influence
    functions, :func:`~eofnn.sim.sensing.least_squares.surface_per_command`); ``measurement_unit``: the same for
    ``wfs`` (default ``command_unit``); everything identified is in eofnn's units; ``optical_gain``: the sensor's
    response to the phase on sky over its calibration's, where the user knows it (the dither identifies only the
    product of the DM's gain and it; a diffractive Shack-Hartmann's spots broadened by the seeing make it less than
    1): the POL is divided by it before the seeing, the layers and the noise (which are then the phase's, not the
    sensor's reading of it: r0 otherwise comes out ``optical_gain^(-6/5)`` high), and the twin's DM gain is the product
    over it (its sensor has none); ``"identified"``: all of the identified product is the optical gain (the DM's gain
    is its interaction matrix's, as where the matrix was measured on this DM); ``seed``: the reference streams'."""
    measurement_unit = command_unit if measurement_unit is None else measurement_unit
    check_units(command_unit, measurement_unit)
    check_value("optical_gain", optical_gain, OPTICAL_GAIN)
    from eofnn.sim.grid import ActuatorGrid, nearest_grid
    from eofnn.sim.layout import layout_from_positions
    from eofnn.training.identify import PlantNotIdentifiedWarning, identify_plant

    result = TwinIdentification()
    if telemetry.positions_m is None:
        raise TelemetryError("telemetry has no actuator positions (positions_m): the twin's pupil, r0 and winds need "
                             "them (docs/telemetry.md)")
    if telemetry.modal_basis is not None:
        raise TelemetryError("telemetry is modal: the twin needs actuator-space y and wfs (modal_basis @ y)")
    y_all, wfs_all = telemetry.y.numpy(), telemetry.wfs.numpy()
    if y_all.ndim == 3:
        y_all, wfs_all = y_all[0], wfs_all[0]
    frames, n_act = y_all.shape
    if frames < MIN_LAYER_FRAMES:
        raise TelemetryError(f"telemetry has {frames} frames: too short to identify a layer (at least "
                             f"{MIN_LAYER_FRAMES} frames)")
    positions = telemetry.positions_m.numpy()
    im = telemetry.interaction_matrix if interaction_matrix is None else interaction_matrix
    rec = telemetry.reconstructor if reconstructor is None else reconstructor
    im = None if im is None else np.asarray(im, dtype=np.float64)
    rec = None if rec is None else np.asarray(rec, dtype=np.float64)
    n_slopes = None if telemetry.slopes is None else int(telemetry.slopes.shape[-1])
    pupil = pupil_from_matrices(n_act, n_slopes, im, rec, positions)
    layout = layout_from_positions(positions)
    pitch = float(layout.pitch_m)
    if isinstance(layout, ActuatorGrid):
        result.grid = {"diameter_m": layout.diameter_m, "n_across": layout.n_across, "obstruction": layout.obstruction}
        if layout.active_diameter_m is not None:
            result.grid["active_diameter_m"] = layout.active_diameter_m
        grid_method = "positions: eofnn's cell-centred grid recognised"
    else:
        result.grid, exact = nearest_grid(positions, pitch)
        grid_method = "positions: lattice extent and pitch " + ("and the active diameter that lists the actuators"
                                                                if exact else "(the nearest eofnn grid)")
        if not exact:
            result.warn(f"the actuators are not eofnn's grid: the twin uses {result.grid['n_across']} across at pitch "
                        f"{pitch:.4g} m")
    e = result.estimates
    e["pupil"] = Estimate({"actuators": n_act, "pitch_m": pitch, **result.grid, **pupil}, None, "m",
                          grid_method + ("; interaction matrix: columns that move slopes, rows that respond"
                                         if im is not None else ""))
    result.sensor = "shack_hartmann" if (im is not None or n_slopes is not None or rec is not None) else "subaperture"
    if result.sensor == "shack_hartmann":
        if mechanical_coupling is None:
            result.warn(f"the DM's influence functions are not in the telemetry: Gaussian, {DEFAULT_COUPLING} one pitch "
                        "away assumed (give mechanical_coupling)")
        else:
            result.mechanical_coupling = float(mechanical_coupling)
        if not isinstance(layout, ActuatorGrid) and pupil["valid_subapertures"]:
            lit = pitch * math.sqrt(4 * pupil["valid_subapertures"] / math.pi)
            if lit < result.grid["diameter_m"] - pitch / 2:
                result.lit_pupil_m = round(lit, 4)
                e["pupil"].value["lit_diameter_m"] = result.lit_pupil_m
                e["pupil"].method += "; lit diameter from the valid subapertures' area, pitch sqrt(4 n / pi)"
    else:  # wfs alone cannot tell a Shack-Hartmann's reconstruction (in commands) from a subaperture average
        result.warn("no slopes, interaction matrix or reconstructor: the subaperture average is assumed (a Shack-"
                    "Hartmann's record without them gives r0 too small: give interaction_matrix or reconstructor)")
    from eofnn.sim.sensing.least_squares import surface_per_command

    peak = surface_per_command(result.mechanical_coupling)
    scale, measured, note = conversion(command_unit, measurement_unit, peak)
    if note:
        y_all, wfs_all, rec = y_all * scale, wfs_all * measured, None if rec is None else rec * measured
        result.warn(f"commands in nm of influence-function peak: y and wfs multiplied by {scale:.4g} (nm of smooth "
                    f"surface per nm of command at coupling {result.mechanical_coupling:g}); all values in eofnn's units"
                    if command_unit == measurement_unit == PEAK else note)
    if telemetry.frame_rate_hz is None:
        result.warn("telemetry has no frame rate (FRATE): 1000 Hz assumed, winds scale with it")
        e["frame_rate_hz"] = Estimate(1000.0, None, "Hz", "assumed", "no frame rate in the file")
    else:
        e["frame_rate_hz"] = Estimate(float(telemetry.frame_rate_hz), 0.0, "Hz", "header (FRATE)")
    result.frame_rate_hz = float(e["frame_rate_hz"].value)
    period = 1.0 / result.frame_rate_hz
    delay = telemetry.delay_frames
    e["delay_frames"] = Estimate(delay, 0.0, "frames", "header (DELAY)")

    # The plant: DM gain x optical gain, from the dither.
    gain, gain_se, gain_method, gain_warning = 1.0, None, "assumed", ""
    from eofnn.telemetry.record import Telemetry

    record = Telemetry(y=torch.as_tensor(y_all), wfs=torch.as_tensor(wfs_all), delay_frames=delay,
                       positions_m=torch.as_tensor(positions))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PlantNotIdentifiedWarning)
        try:
            plant = identify_plant(record) if float(delay).is_integer() else None
        except TelemetryError as err:
            plant, gain_warning = None, str(err)
    if plant is not None and plant.identified:
        gain, gain_se = float(plant.dm_gain), float(plant.dm_gain_se)
        gain_method = "eofnn identify: the response of wfs to the dither's innovations"
        e["lag_frames"] = Estimate(int(plant.lag_frames), 0, "frames", "where the response to the dither peaks")
        for warning in plant.warnings:
            result.warn(f"plant: {warning}")
    else:
        gain_warning = gain_warning or ("no dither in the record: the DM gain x optical gain is not identifiable; 1 "
                                        "assumed (record with a white dither of a few nm)")
        result.warn(gain_warning)
    e["dm_gain"] = Estimate(gain, gain_se, "", gain_method, gain_warning)

    pol = pseudo_open_loop(y_all, wfs_all, gain, delay)
    if optical_gain is not None:  # the phase's POL, not the sensor's reading of it
        identified = optical_gain == "identified"
        how = ("identified: the DM's gain taken as its interaction matrix's (calibrated on this DM), so all of "
               "dm_gain is the sensor's" if identified else "given (the user's knowledge of the sensor)")
        e["optical_gain"] = Estimate(gain if identified else float(optical_gain), gain_se if identified else None, "",
                                     how + "; the POL divided by it, the twin's DM gain dm_gain over it")
        pol = pol / e["optical_gain"].value
    else:
        result.warn("r0 and the noise are of the sensor's reading of the phase: its optical gain on sky is not "
                    "identifiable (the dither gives the DM gain x it); a diffractive sensor's r0 comes out "
                    "optical_gain^(-6/5) high (give optical_gain where known)")
    pol = pol - pol.mean(0)
    parts = record_blocks(frames, blocks)

    # The POL carries piston/tip/tilt unless the loop removed them.
    ptt = pol @ ptt_projector(positions)
    kept = 1 - float(np.mean(ptt.var(0))) / max(float(np.mean(pol.var(0))), 1e-300)
    result.remove_ptt = kept < 0.02

    # Layers.
    lattice = Lattice(layout)
    layers, info = identify_layers(pol, lattice, period, max_layers=max_layers, max_speed_mps=max_speed_mps,
                                   blocks=blocks)
    result.layers = layers
    e["layers"] = Estimate(len(layers), None, "", f"lagged cross-spectra of whitened POL maps (control/wind.py) with "
                           f"1-{max_layers} layers, winds searched up to {info['search_mps']} m/s (longest lag: "
                           f"{info['shift_pitches']:g} pitches at that speed), layers added while "
                           f"each is found again in every block and carries {MIN_EXTRA_WEIGHT:.0%} or more (BIC "
                           f"{info['bic']}{'; ' + info['stopped'] if info['stopped'] else ''}), layers within "
                           f"{MERGE_SPEED_MPS} m/s merged; winds' errors from {blocks} blocks")

    # r0, L0 and the noise together, against the twin's own sensor at a reference r0.
    config = result.scenario_config(noise_magnitude=8.0, r0_m=R0_REFERENCE_M, outer_scale_m=OUTER_SCALES_M[0])
    config["plant"]["wfs_noise_nm"] = 0.0
    references = reference_covariances(config, layers, min(frames, REFERENCE_FRAMES), seed=seed, record=(rec, positions))
    cv, seeing = seeing_and_noise(pol, references, positions, pitch)
    fits = [seeing_and_noise(pol[s], references, positions, pitch) for s in parts]
    sensing = ("eofnn's Shack-Hartmann (Fried, Gaussian influence functions of coupling "
               f"{result.mechanical_coupling:g})" if result.sensor == "shack_hartmann" else "the subaperture average")
    method = (f"noise-corrected POL covariance against the twin's ({sensing}) at r0 = {R0_REFERENCE_M} m over "
              f"{2 * min(frames, REFERENCE_FRAMES)} noise-free frames: the structure function (piston, tip, tilt "
              "projected out) over 1.5 pitches to half the pupil scales as r0^(-5/3)")
    e["r0_m"] = Estimate(seeing["r0_m"], standard_error([f[1]["r0_m"] for f in fits]), "m at 500 nm", method)
    l0s = [f[1]["outer_scale_m"] for f in fits]
    misfit = seeing["misfit"]
    l0_warning = ""
    if len(set(l0s)) > 1 or sorted(misfit.values())[1] < 1.2 * min(misfit.values()):
        l0_warning = (f"L0 not identifiable from this record (pupil {result.grid['diameter_m']:.3g} m, blocks gave "
                      f"{sorted(l0s)} m): the twin keeps the best fit")
        result.warn(l0_warning)
    e["outer_scale_m"] = Estimate(seeing["outer_scale_m"], standard_error(np.log(l0s)) * seeing["outer_scale_m"], "m",
                                  f"the outer scale of {list(OUTER_SCALES_M)} whose structure function fits best "
                                  f"(rms log misfit {misfit})", l0_warning)

    per_act = np.clip(np.diag(cv), 0, None)
    e["wfs_noise_nm"] = Estimate(math.sqrt(float(per_act.mean())),
                                 standard_error([math.sqrt(max(float(np.diag(f[0]).mean()), 0)) for f in fits]), "nm",
                                 "white floor of the POL's cross-periodogram at 0.25-0.5 cycles/frame beside an f^(-11/3) "
                                 f"tail, less the share ({seeing['aliasing_share']:.2f}) of the twin's own floor there that "
                                 "the record's spectrum at 0.19-0.25 cycles/frame shows; RMS over actuators")
    e["wfs_noise_per_actuator_nm"] = Estimate(np.sqrt(per_act).round(4).tolist(), None, "nm", "diagonal of C_v")
    neighbours = layout.neighbours(1.0).numpy()
    corr = cv / np.sqrt(np.outer(per_act, per_act) + 1e-300)
    nearest = [corr[k, j] for k in range(n_act) for j in neighbours[k, 1:] if j < n_act and per_act[k] * per_act[j] > 0]
    colour = {"nearest_neighbour_correlation": float(np.mean(nearest)) if nearest else None}  # pairs with noise
    colour_method = "off-diagonal of C_v: the mean correlation of nearest neighbours' noise"
    if rec is not None:
        rr = rec @ rec.T
        slope = float(np.sum(cv * rr) / np.sum(rr * rr))
        colour["slope_noise_rms"] = math.sqrt(max(slope, 0))
        colour["model_misfit"] = float(np.linalg.norm(cv - slope * rr) / np.linalg.norm(cv))
        colour_method += "; C_v fitted as sigma² R R^T (slope noise in slope units, white and equal)"
    e["wfs_noise_colour"] = Estimate(colour, None, "", colour_method)
    return result
