"""The conditions a predictor was trained in, recorded in its checkpoint, and a one-line warning when it is used in
others.

A predictor fitted to a measurement learns that measurement's noise: fitted on noise-free telemetry and replayed on
noisy telemetry, it passes the noise back at unit gain (in OOPAO's loop such an EOF did worse than the loop's
integrator, and nothing said why: ``docs/findings.md``). So a checkpoint keeps, in ``info["conditions"]``:

- ``wfs_noise_nm``: the WFS noise per actuator and frame (nm RMS) of the training data: the scenario's, or the one
  identified from the telemetry;
- ``dm_gain``: the DM gain of the loop it was fitted for (the scenario's, or the identified or given one);
- ``wind_speeds_mps``: the layers' wind speeds (m/s) when trained in simulation (telemetry does not tell them);
- ``source``: where those values come from.

:func:`shift_warnings` compares them with the conditions a predictor meets (a scenario's plant, or a plant
identified from the telemetry it is replayed on) and says, one line per quantity, what differs beyond
:data:`TOLERANCES`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass

from eofnn.errors import ShiftWarning

#: What counts as a shift: noise by more than a factor 1.5 *and* 0.5 nm (both: 0.1 against 0.2 nm is no shift that
#: matters, 0 against 2 nm is); DM gain by more than 10%; the mean wind speed by more than a factor 1.3.
TOLERANCES = {"wfs_noise_factor": 1.5, "wfs_noise_nm": 0.5, "dm_gain_relative": 0.10, "wind_speed_factor": 1.3}


@dataclass(frozen=True)
class Conditions:
    """What a predictor sees: WFS noise (nm RMS per actuator and frame), DM gain, wind speeds (m/s), and where they
    come from. ``None`` where unknown."""

    wfs_noise_nm: float | None
    dm_gain: float | None
    wind_speeds_mps: tuple[float, ...] | None
    source: str

    def to_dict(self) -> dict:
        out = asdict(self)
        out["wind_speeds_mps"] = None if self.wind_speeds_mps is None else list(self.wind_speeds_mps)
        return out

    @classmethod
    def from_dict(cls, values: dict | None) -> Conditions | None:
        """The conditions a checkpoint recorded, or ``None`` for one written before they were (or not a mapping)."""
        if not isinstance(values, dict):
            return None
        winds = values.get("wind_speeds_mps")
        return cls(_number(values.get("wfs_noise_nm")), _number(values.get("dm_gain")),
                   None if not isinstance(winds, (list, tuple)) else tuple(float(w) for w in winds
                                                                           if _number(w) is not None),
                   str(values.get("source", "unknown")))


def _number(value) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(
        value) else None


def scenario_conditions(scenario, dm_gain: float | None = None) -> Conditions:
    """The conditions of a simulated ``scenario`` (its plant's WFS noise and DM gain, its layers' winds);
    ``dm_gain`` overrides the plant's (an open-loop filter believes 1). With a Shack-Hartmann the noise is what its
    slope noise (photon, read and the plant's) leaves per actuator: ``sigma sqrt(trace(R W R^T) / K)`` (``W``: the
    partly lit subapertures' larger noise, the identity without them)."""
    noise = float(scenario.plant.wfs_noise_nm)
    if scenario.sensor.is_shack_hartmann:
        sensed = scenario.turbulence(0, "conditions")
        reconstructor = sensed.operators.reconstructor
        scale = sensed.operators.sensor.slope_noise_scale
        power = reconstructor.pow(2) if (scale == 1).all() else reconstructor.pow(2).numpy() * scale ** 2
        noise = sensed.slope_noise_nm(noise) * math.sqrt(float(power.sum()) / reconstructor.shape[0])
    return Conditions(noise,
                      float(scenario.plant.dm_gain if dm_gain is None else dm_gain),
                      tuple(float(layer.wind_speed_mps) for layer in scenario.atmosphere.layers), "scenario")


def plant_conditions(plant, source: str) -> Conditions:
    """The conditions of a plant identified from telemetry (``wfs_noise_nm``, ``dm_gain``: attributes, possibly
    ``None``) or given as a mapping of model errors (``dm_gain``, ``wfs_noise_nm``); winds unknown."""
    if isinstance(plant, dict):
        return Conditions(_number(plant.get("wfs_noise_nm")), _number(plant.get("dm_gain", 1.0)), None, source)
    return Conditions(_number(getattr(plant, "wfs_noise_nm", None)), _number(getattr(plant, "dm_gain", None)), None,
                      source)


def shift_warnings(trained: Conditions | None, now: Conditions, what: str) -> list[str]:
    """One line per quantity that differs beyond :data:`TOLERANCES` between the training conditions and ``now``
    (nothing when either is unknown). ``what`` names the predictor and where it is used, e.g. ``"replay of cl.ckpt
    on held.fits"``."""
    if trained is None:
        return []
    out = []
    a, b = trained.wfs_noise_nm, now.wfs_noise_nm
    if a is not None and b is not None and abs(a - b) > TOLERANCES["wfs_noise_nm"] and (
            min(a, b) == 0 or max(a, b) / min(a, b) > TOLERANCES["wfs_noise_factor"]):
        effect = ("it has not learnt to filter this noise and passes it back" if b > a else
                  "it filters noise that is no longer there, at a cost in lag")
        out.append(f"{what}: trained at {a:.3g} nm of WFS noise ({trained.source}), used at {b:.3g} nm "
                   f"({now.source}): {effect}; refit on data like these (tolerance: a factor "
                   f"{TOLERANCES['wfs_noise_factor']:g} and {TOLERANCES['wfs_noise_nm']:g} nm)")
    a, b = trained.dm_gain, now.dm_gain
    if a is not None and b is not None and a > 0 and abs(b / a - 1) > TOLERANCES["dm_gain_relative"]:
        out.append(f"{what}: trained for a DM gain of {a:.3g} ({trained.source}), used at {b:.3g} ({now.source}): "
                   f"check its stable DM-gain interval (tolerance: {TOLERANCES['dm_gain_relative']:.0%})")
    a_w, b_w = trained.wind_speeds_mps, now.wind_speeds_mps
    if a_w and b_w:
        mean_a, mean_b = sum(a_w) / len(a_w), sum(b_w) / len(b_w)
        if min(mean_a, mean_b) > 0 and max(mean_a, mean_b) / min(mean_a, mean_b) > TOLERANCES["wind_speed_factor"]:
            out.append(f"{what}: trained at a mean wind of {mean_a:.3g} m/s ({trained.source}), used at "
                       f"{mean_b:.3g} m/s ({now.source}): its prediction assumes the old speed (tolerance: a factor "
                       f"{TOLERANCES['wind_speed_factor']:g})")
    return out


def warn_shift(trained: dict | None, now: Conditions, what: str) -> list[str]:
    """:func:`shift_warnings` of a checkpoint's recorded ``info["conditions"]`` against ``now``, each line also
    issued as a :class:`~eofnn.errors.ShiftWarning` (the command line prints it as one ``eofnn: warning:`` line)."""
    lines = shift_warnings(Conditions.from_dict(trained), now, what)
    for line in lines:
        warnings.warn(line, ShiftWarning, stacklevel=2)
    return lines
