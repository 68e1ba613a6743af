"""A twin of the user's system identified from its closed-loop telemetry alone (``eofnn twin``).

What a real loop records: the commands ``y``, the measurements ``wfs`` (or slopes with an interaction matrix or a
reconstructor), the dither if one was added, the actuator positions, the delay and the frame rate. Nothing here reads
the simulator's truth (``s``, ``eps``) or its configuration; every quantity comes with an uncertainty and the method
that gave it, and a quantity the record cannot tell is given with a one-line warning and the value assumed.

1. *The pupil* (:func:`pupil_from_matrices`): the actuators are the columns of ``y`` at their positions; an
   interaction matrix says which of them move the slopes (a column of almost zero is an actuator outside the lit
   pupil: refused, since the telemetry controls it) and which slopes respond (the valid subapertures); a
   reconstructor must be ``(K, S)``.
2. *The plant*: the DM gain times the optical gain and the WFS lag by :func:`eofnn.training.identify.identify_plant`
   when the record holds a dither; without one it is not identifiable and 1 is assumed. The delay is the file's.
3. *The pseudo-open-loop signal* ``s_hat(n) = wfs(n) - g y(n)`` (eofnn's alignment, ``docs/telemetry.md``: ``wfs(n)``
   measures ``s(n) + g y(n)``; a fractional delay ``d + f`` averages the commands, ``(1 - f) y(n) + f y(n - 1)``).
4. *The WFS noise* (:func:`noise_covariance`): white noise ``v`` adds ``2 C_v`` to the lagged structure matrix
   ``D(l) = E[(s_hat(n + l) - s_hat(n)) (s_hat(n + l) - s_hat(n))^T]`` at every lag ``l >= 1``, while turbulence
   that is smooth over a few frames adds ``c l^2``: ``C_v = (4 D(1) - D(2)) / 6``, per actuator (its diagonal) and
   between actuators (its spatial colour, compared with ``sigma^2 R R^T`` when a reconstructor is given).
5. *r0 and L0* (:func:`seeing_and_noise`, :func:`fit_seeing`): the noise-corrected covariance of ``s_hat`` against
   the covariance of the twin's own noise-free turbulence (:func:`reference_covariances`: the twin's grid, sensor
   and identified winds, simulated at r0 = :data:`R0_REFERENCE_M` for each L0 of :data:`OUTER_SCALES_M`), so that
   the sensing (a subaperture average, or a Shack-Hartmann's reconstruction with its aliasing, in command units)
   is the twin's: their structure functions over actuator separations from 1.5 pitches to half the pupil, piston,
   tip and tilt projected out of both, differ by the factor ``(r0 / r0_ref)^(-5/3)`` (r0 at
   :data:`R0_WAVELENGTH_M`); L0 is the one whose shape fits best (not identifiable on a pupil much smaller than L0:
   one line says so and the twin keeps the best fit). A Shack-Hartmann's aliased turbulence is not smooth over two
   frames and leaves part of itself in the noise estimate of 4; the references say how much per unit of their
   turbulence, so the noise and r0 are solved for together.
6. *The layers* (:func:`identify_layers`): :func:`eofnn.control.wind.identify_winds` (lagged cross-spectra of the
   whitened POL maps: a frozen-flow layer's peak moves by ``v tau``) fitted with 1 to ``max_layers`` layers, the
   count chosen by the record's own consistency: a layer is added only if every block of the record finds it again
   with the same wind, and it carries a fair share of the turbulence (an aliased Shack-Hartmann's modes have an
   apparent motion that a cross-spectrum fit takes for a weak extra layer, whose wind changes from block to block);
   layers closer than :data:`MERGE_SPEED_MPS` are merged, and the winds' spread over the blocks gives the
   uncertainty. A Bayesian information criterion on the cross-spectra's residual is reported beside it, not used:
   the cross-spectra's values are not independent, and it takes the aliased component for a layer.

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

torch = lazy_module("torch")

#: The wavelength r0 is given at (m).
R0_WAVELENGTH_M = 5e-7
#: Outer scales (m) the structure function is fitted over.
OUTER_SCALES_M = (10.0, 20.0, 40.0)
#: The r0 (m, at :data:`R0_WAVELENGTH_M`) of the reference turbulence the record's is scaled from.
R0_REFERENCE_M = 0.1
#: Frames of each reference stream (at most; two realisations).
REFERENCE_FRAMES = 3000
#: The DM's influence functions when the record has slopes and no coupling is given: Gaussian, this value one pitch
#: away (OOPAO's and eofnn's default).
DEFAULT_COUPLING = 0.35
#: Layers whose winds differ by less than this (m/s) are one layer.
MERGE_SPEED_MPS = 2.0
#: An interaction-matrix column (row) below this fraction of the median column (row) norm moves (answers) nothing.
DEAD_FRACTION = 1e-3
#: A layer's wind is consistent over the record's blocks when their standard errors are below these (degrees; a
#: fraction of its speed).
CONSISTENT_DIRECTION_DEG = 5.0
CONSISTENT_SPEED = 0.08
#: A layer beyond the first must carry at least this share of the turbulence.
MIN_EXTRA_WEIGHT = 0.15
#: The wind search is bounded by this times the fastest wind of a first fit, and at least by this speed (m/s).
SEARCH_MARGIN = 1.5
SLOWEST_BOUND_MPS = 10.0
#: The refined search's longest lag: the time the bound speed takes to cross this fraction of the pupil (at least
#: :data:`eofnn.control.wind.LONGEST_SHIFT_PITCHES`). Measured on 16 actuators across: with a quarter (wind.py's
#: default) 8 and 13 m/s along one direction merge into one layer; with a half a 20 m/s layer beside a 9 m/s one
#: is lost (too little overlap left); 3/8 parts both.
LONGEST_SHIFT_OF_PUPIL = 0.375
#: What one nm of command may be: of smooth DM surface (eofnn's) or at an influence function's peak (OOPAO's).
COMMAND_UNITS = ("surface", "peak")
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
            "plant": {"delay_frames": self.value("delay_frames"), "dm_gain": round(float(self.value("dm_gain")), 4)},
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


def twin_magnitude(config: dict, noise_nm: float, start: float = 8.0) -> float:
    """The R magnitude of a Shack-Hartmann twin's guide star whose photon noise per actuator is ``noise_nm``
    (:func:`eofnn.training.conditions.scenario_conditions`: photon noise scales as ``10^(0.2 m)``)."""
    from eofnn.sim.scenario import Scenario
    from eofnn.training.conditions import scenario_conditions

    cfg = json.loads(json.dumps(config))
    cfg["sensor"]["detector"]["magnitude"] = start
    own = scenario_conditions(Scenario.from_dict(cfg)).wfs_noise_nm
    return start + 5 * math.log10(noise_nm / own)


# ----------------------------------------------------------------------------------------------------------- pupil

def pupil_from_matrices(n_actuators: int, n_slopes: int | None, interaction_matrix=None, reconstructor=None,
                        positions_m=None) -> dict:
    """The actuators the interaction matrix sees and the slopes that respond, the reconstructor's shape checked.

    Returns ``{"valid_slopes": int or None, "valid_subapertures": int or None, "dead_slopes": list}``.

    Raises
    ------
    TelemetryError
        A reconstructor that is not ``(K, S)``; an interaction matrix that is not ``(S, K)``; an actuator of the
        telemetry (a column of ``y``) whose interaction-matrix column is about zero (the telemetry's mask and the
        matrix disagree).
    """
    out: dict = {"valid_slopes": None, "valid_subapertures": None, "dead_slopes": []}
    im = None if interaction_matrix is None else np.asarray(interaction_matrix, dtype=np.float64)
    if im is not None and n_slopes is None:
        n_slopes = im.shape[0]
    if reconstructor is not None:
        r = np.asarray(reconstructor)
        s = n_slopes if n_slopes is not None else (r.shape[1] if r.ndim == 2 else None)
        if r.ndim != 2 or r.shape[0] != n_actuators or s is None or r.shape[1] != s or s % 2:
            expected = f"({n_actuators}, 2 n_sub) = ({n_actuators}, {s})" if s else f"({n_actuators}, 2 n_sub)"
            raise TelemetryError(f"reconstructor has shape {r.shape}: expected {expected}, wfs = R @ slopes for "
                                 f"{n_actuators} actuators and x then y slopes of n_sub subapertures")
    if im is None:
        return out
    if im.ndim != 2 or im.shape != (n_slopes, n_actuators):
        raise TelemetryError(f"interaction_matrix has shape {im.shape}: expected ({n_slopes}, {n_actuators}) "
                             "(slopes = IM @ y)")
    columns = np.linalg.norm(im, axis=0)
    dead = np.flatnonzero(columns < DEAD_FRACTION * np.median(columns))
    if dead.size:
        where = "" if positions_m is None else f" at ({positions_m[dead[0]][0]:.3g}, {positions_m[dead[0]][1]:.3g}) m"
        raise TelemetryError(f"the telemetry's actuators and its interaction matrix disagree: {dead.size} actuator(s) "
                             f"(first: column {int(dead[0])}{where}) move no slope (IM column about 0): drop them from "
                             "y, wfs and positions, or give the interaction matrix of this loop")
    rows = np.linalg.norm(im, axis=1)
    valid = rows >= DEAD_FRACTION * np.median(rows)
    out.update(valid_slopes=int(valid.sum()), valid_subapertures=int(valid.sum()) // 2,
               dead_slopes=np.flatnonzero(~valid).tolist())
    return out


class _Lattice:
    """Actuators on a square lattice as :class:`~eofnn.control.fourier.FourierBasis` reads eofnn's grid (row-major
    ``indices``, ``pitch_m``, ``n_across``, ``neighbours``); ``order`` takes the telemetry's columns to it."""

    def __init__(self, layout) -> None:
        from eofnn.sim.grid import ActuatorGrid
        from eofnn.sim.layout import ActuatorLayout

        lattice = layout.indices if isinstance(layout, ActuatorGrid) else layout.lattice_indices
        if lattice is None:
            raise TelemetryError("identifying layers needs the actuators on a square lattice: these positions are "
                                 "not (give the twin's winds by hand)")
        lattice = np.asarray(lattice) - np.asarray(lattice).min(0)
        self.order = np.lexsort((lattice[:, 1], lattice[:, 0]))
        self.indices = lattice[self.order]
        positions = np.asarray(layout.positions_m)[self.order]
        self.positions_m = positions
        self.pitch_m = float(layout.pitch_m)
        self.n_across = int(lattice.max()) + 1
        self.n_actuators = len(lattice)
        self._layout = ActuatorLayout(positions)

    def neighbours(self, radius: float):
        return self._layout.neighbours(radius)

    def ptt_basis(self) -> np.ndarray:
        return self._layout.ptt_basis()


# ------------------------------------------------------------------------------------------------------ statistics

def pseudo_open_loop(y: np.ndarray, wfs: np.ndarray, dm_gain: float, delay_frames: float) -> np.ndarray:
    """``s_hat(n) = wfs(n) - g DM-term(n)`` (module docstring, 3), ``(frames, K)`` nm."""
    fraction = float(delay_frames) - math.floor(float(delay_frames))
    acting = y if fraction == 0 else np.concatenate([y[:1], (1 - fraction) * y[1:] + fraction * y[:-1]])
    return wfs - dm_gain * acting


def noise_covariance(pol: np.ndarray) -> np.ndarray:
    """``C_v = (4 D(1) - D(2)) / 6`` (module docstring, 4), ``(K, K)`` nm², of ``(frames, K)`` POL values."""
    d1, d2 = pol[1:] - pol[:-1], pol[2:] - pol[:-2]
    return (4 * d1.T @ d1 / len(d1) - d2.T @ d2 / len(d2)) / 6


def _blocks(frames: int, blocks: int) -> list[slice]:
    size = frames // blocks
    return [slice(i * size, (i + 1) * size) for i in range(blocks)]


def _se(values) -> float:
    values = np.asarray(values, dtype=np.float64)
    return float(values.std(ddof=1) / math.sqrt(len(values))) if len(values) > 1 else float("nan")


def _ptt_projector(positions: np.ndarray) -> np.ndarray:
    basis = np.column_stack([np.ones(len(positions)), positions - positions.mean(0)])
    q, _ = np.linalg.qr(basis)
    return np.eye(len(positions)) - q @ q.T


def reference_covariances(config: dict, layers: list[dict], frames: int, *, realisations: int = 2,
                          seed: int = 0) -> dict[float, np.ndarray]:
    """``{L0: (cov, leak, positions)}``: the ``(K', K')`` covariance (nm²) and :func:`noise_covariance` of the
    noise-free turbulence, and the ``(K', 2)`` positions (m) of the twin's actuators, as the twin's sensor sees it, at
    ``r0 =`` :data:`R0_REFERENCE_M` (at :data:`R0_WAVELENGTH_M`) and each outer scale of :data:`OUTER_SCALES_M`, the
    identified winds, over ``realisations`` streams of ``frames`` frames (``config``: the twin's scenario fields)."""
    from eofnn.sim.scenario import Scenario

    out = {}
    for l0 in OUTER_SCALES_M:
        cfg = json.loads(json.dumps(config))
        cfg["atmosphere"].update(r0_m=R0_REFERENCE_M, r0_wavelength_m=R0_WAVELENGTH_M, outer_scale_m=l0,
                                 screen_frames=frames,
                                 layers=[{"cn2_fraction": lay["weight"], "wind_speed_mps": lay["speed_mps"],
                                          "wind_direction_deg": lay["direction_deg"]} for lay in layers])
        cfg["plant"]["wfs_noise_nm"] = 0.0
        if "sensor" in cfg:
            cfg["sensor"]["detector"] = None
        scenario = Scenario.from_dict(cfg)
        s = scenario.turbulence(seed, "twin_reference", realisations).frames(0, frames).numpy()
        out[l0] = (sum(np.cov(r.T) for r in s) / len(s), sum(noise_covariance(r) for r in s) / len(s),
                   np.asarray(scenario.grid.positions_m))
    return out


def _structure(cov: np.ndarray, distance: np.ndarray, bins: np.ndarray) -> np.ndarray:
    d = np.diag(cov)
    pairs = d[:, None] + d[None, :] - 2 * cov
    which = np.digitize(distance, bins)
    return np.array([pairs[which == b].mean() if (which == b).any() else np.nan for b in range(1, len(bins))])


def seeing_and_noise(pol: np.ndarray, references: dict, positions_m: np.ndarray, pitch_m: float,
                     iterations: int = 4) -> tuple[np.ndarray, dict]:
    """``(C_v, seeing)``: the noise covariance and :func:`fit_seeing` of ``(frames, K)`` POL values, together.
    Turbulence that is not smooth over two frames (an aliased Shack-Hartmann's) leaves part of itself in
    :func:`noise_covariance`; the references tell how much per unit of their turbulence (their own
    :func:`noise_covariance`, scaling as ``r0^(-5/3)``), so that part is removed at the r0 found, and r0 fitted
    again with the noise so corrected."""
    raw, total = noise_covariance(pol), np.cov(pol.T)
    cv, seeing = raw, fit_seeing(total - raw, references, positions_m, pitch_m)
    for _ in range(iterations):
        _, leak, where = references[seeing["outer_scale_m"]]
        if leak.shape != raw.shape or not np.allclose(where, positions_m):  # another layout: its mean, per actuator
            leak = np.eye(len(raw)) * float(np.diag(leak).mean())
        cv = raw - leak * (R0_REFERENCE_M / seeing["r0_m"]) ** (5 / 3)
        seeing = fit_seeing(total - cv, references, positions_m, pitch_m)
    return cv, seeing


def fit_seeing(turbulence_cov: np.ndarray, references: dict[float, np.ndarray], positions_m: np.ndarray,
               pitch_m: float) -> dict:
    """r0 (m, at :data:`R0_WAVELENGTH_M`) and L0 (m) of a ``(K, K)`` turbulence covariance against the
    :func:`reference_covariances` (module docstring, 5): ``{"r0_m", "outer_scale_m", "misfit": {L0: rms log
    misfit}}``. The structure function ``D(r)`` of each, piston, tip and tilt projected out, averaged over pairs
    of actuators in bins of a pitch from 1.5 pitches to half the pupil; ``D`` scales as ``r0^(-5/3)``."""
    def structure(cov: np.ndarray, positions: np.ndarray) -> np.ndarray:
        p = _ptt_projector(positions)
        return _structure(p @ cov @ p, np.linalg.norm(positions[:, None] - positions[None], axis=-1), bins)

    extent = float(np.ptp(positions_m, axis=0).max())
    bins = np.arange(1.5 * pitch_m, max(0.5 * extent, 3 * pitch_m) + pitch_m / 2, pitch_m)
    measured = structure(turbulence_cov, positions_m)
    results = {}
    for l0, (reference, _, where) in references.items():
        model = structure(reference, where)
        good = np.isfinite(measured) & (measured > 0) & np.isfinite(model) & (model > 0)
        ratio = np.log(measured[good] / model[good])
        results[l0] = (float(ratio.mean()), float(ratio.std()))
    best = min(results, key=lambda k: results[k][1])
    return {"r0_m": float(R0_REFERENCE_M * math.exp(-0.6 * results[best][0])), "outer_scale_m": best,
            "misfit": {str(k): round(v[1], 4) for k, v in results.items()}}


# --------------------------------------------------------------------------------------------------------- layers

def _layer_fit(pol_lattice: np.ndarray, lattice: _Lattice, period: float, n_layers: int, max_speed: float,
               shift_pitches: float | None = None):
    """Layers and the residual sum of squares of their cross-spectra model (weights refitted by least squares)."""
    from eofnn.control.fourier import FourierBasis
    from eofnn.control.wind import HIGHEST_CYCLES_PER_PITCH, cross_spectra, identify_winds, wind_lags

    basis = FourierBasis(lattice)
    pol = torch.as_tensor(pol_lattice[None])
    layers = identify_winds(pol, basis, period, n_layers, max_speed, shift_pitches)
    norm = basis.frequencies.norm(dim=1)
    keep = (norm <= HIGHEST_CYCLES_PER_PITCH / lattice.pitch_m) & (norm > 0)
    lags = wind_lags(lattice.n_across, lattice.pitch_m, max_speed, period, pol.shape[1], shift_pitches)
    spectra = cross_spectra(pol, basis, lags, keep).numpy()
    x0, data = spectra[0], spectra[1:]
    f = basis.frequencies[keep].numpy()
    lag_s = np.asarray(lags, dtype=float) * period
    columns = [(x0[None] * np.exp(-2j * np.pi * lag_s[:, None] * (f @ [lay["vx_mps"], lay["vy_mps"]])[None])).ravel()
               for lay in layers]
    a = np.stack(columns, 1)
    a2 = np.concatenate([a.real, a.imag])
    b2 = np.concatenate([data.ravel().real, data.ravel().imag])
    weights, *_ = np.linalg.lstsq(a2, b2, rcond=None)
    rss = float(np.sum((a2 @ weights - b2) ** 2))
    return layers, rss, b2.size


def _merged(layers: list[dict]) -> list[dict]:
    out: list[dict] = []
    for lay in layers:
        for kept in out:
            if math.hypot(lay["vx_mps"] - kept["vx_mps"], lay["vy_mps"] - kept["vy_mps"]) < MERGE_SPEED_MPS:
                total = kept["weight"] + lay["weight"]
                for key in ("vx_mps", "vy_mps"):
                    kept[key] = (kept[key] * kept["weight"] + lay[key] * lay["weight"]) / total
                kept["weight"] = total
                break
        else:
            out.append(dict(lay))
    for lay in out:
        lay["speed_mps"] = math.hypot(lay["vx_mps"], lay["vy_mps"])
        lay["direction_deg"] = math.degrees(math.atan2(lay["vy_mps"], lay["vx_mps"]))
    return out


def _with_errors(layers: list[dict], blocks: list[list[dict]]) -> list[dict]:
    """``layers`` with the standard errors of each over the blocks' layers (each block's nearest in wind, every
    block's layers used once) and ``found_again``: whether every block has a layer of its own within
    :data:`MERGE_SPEED_MPS` or a quarter of its speed."""
    matched: list[list[dict]] = [[] for _ in layers]
    found_again = [True] * len(layers)
    for block in blocks:
        free = list(block)
        for i in np.argsort([-lay["weight"] for lay in layers]):
            lay = layers[i]
            if not free:
                found_again[i] = False
                matched[i].append(min(block, key=lambda f: _distance(f, lay)))
                continue
            near = min(free, key=lambda f: _distance(f, lay))
            free.remove(near)
            found_again[i] &= _distance(near, lay) <= max(MERGE_SPEED_MPS, 0.25 * lay["speed_mps"])
            matched[i].append(near)
    out = []
    for lay, near, again in zip(layers, matched, found_again, strict=True):
        lay = dict(lay, found_again=bool(again))
        for key in ("vx_mps", "vy_mps", "speed_mps", "weight"):
            lay[key + "_se"] = _se([m[key] for m in near])
        angles = np.radians([m["direction_deg"] for m in near])
        mean = math.atan2(np.sin(angles).mean(), np.cos(angles).mean())
        lay["direction_deg_se"] = math.degrees(_se(np.angle(np.exp(1j * (angles - mean)))))
        out.append(lay)
    return out


def _distance(a: dict, b: dict) -> float:
    return math.hypot(a["vx_mps"] - b["vx_mps"], a["vy_mps"] - b["vy_mps"])


def _consistent(lay: dict) -> bool:
    """A layer every block finds again, with the same wind: direction within :data:`CONSISTENT_DIRECTION_DEG`,
    speed within :data:`CONSISTENT_SPEED` (standard errors)."""
    return lay["found_again"] and lay["direction_deg_se"] <= CONSISTENT_DIRECTION_DEG and lay["speed_mps_se"] <= (
        CONSISTENT_SPEED * lay["speed_mps"])


def identify_layers(pol: np.ndarray, lattice: _Lattice, period: float, *, max_layers: int = 3,
                    max_speed_mps: float = 40.0, blocks: int = 4) -> tuple[list[dict], dict]:
    """Frozen-flow layers of ``(frames, K)`` POL values (columns in the telemetry's order) with uncertainties
    (module docstring, 6): ``(layers, info)``; each layer has ``vx_mps, vy_mps, speed_mps, direction_deg, weight``
    and their ``*_se``.

    First a fit of ``max_layers`` layers up to ``max_speed_mps`` finds the fastest wind; the search is then bounded
    by :data:`SEARCH_MARGIN` times it (at least :data:`SLOWEST_BOUND_MPS`) and the longest lag is the time that
    bound takes to cross :data:`LONGEST_SHIFT_OF_PUPIL` of the pupil (:func:`eofnn.control.wind.wind_lags`: a quarter
    by default), so that a slow layer moves far enough to be measured and two close winds' peaks part. The model order:
    ``n`` layers are accepted while every one of them is found again, with the same wind, in each block of the
    record (:func:`_consistent`) and each added layer carries at least :data:`MIN_EXTRA_WEIGHT` of the turbulence;
    a component that fails (an aliased mode's apparent motion, noise) stops the search at the last order whose
    layers all passed."""
    from eofnn.control.wind import LONGEST_SHIFT_PITCHES

    x = pol[:, lattice.order]
    first, _, _ = _layer_fit(x, lattice, period, max_layers, max_speed_mps)
    fastest = max(lay["speed_mps"] for lay in _merged(first))
    bound = min(max_speed_mps, max(SLOWEST_BOUND_MPS, SEARCH_MARGIN * fastest))
    shift = max(LONGEST_SHIFT_PITCHES, LONGEST_SHIFT_OF_PUPIL * lattice.n_across)
    chosen, scores, why = None, {}, ""
    for n in range(1, max_layers + 1):
        layers, rss, size = _layer_fit(x, lattice, period, n, bound, shift)
        layers = _merged(layers)
        scores[str(n)] = round(size * math.log(rss / size) + 3 * len(layers) * math.log(size), 1)
        if chosen is not None and len(layers) <= len(chosen):
            break  # merged back: no new layer
        found = [_merged(_layer_fit(x[part], lattice, period, n, bound, shift)[0]) for part in _blocks(len(x), blocks)]
        layers = _with_errors(layers, found)
        if chosen is not None:
            weak = [lay for lay in layers if lay["weight"] < MIN_EXTRA_WEIGHT]
            moving = [lay for lay in layers if not _consistent(lay)]
            if weak or moving:
                why = (f"{len(layers)} layers rejected: "
                       + ("a component's wind differs between blocks of the record" if moving else
                          f"a component carries {min(lay['weight'] for lay in weak):.0%} of the turbulence"))
                break
        chosen = layers
    return chosen, {"bic": scores, "chosen": len(chosen), "stopped": why, "search_mps": round(bound, 2),
                    "shift_pitches": shift}


# ----------------------------------------------------------------------------------------------------------- whole

def identify_twin(telemetry, *, interaction_matrix=None, reconstructor=None, max_layers: int = 3,
                  max_speed_mps: float = 40.0, blocks: int = 4, mechanical_coupling: float | None = None,
                  command_unit: str = "surface", seed: int = 0) -> TwinIdentification:
    """Identify the twin of the system that recorded ``telemetry`` (a :class:`~eofnn.telemetry.record.Telemetry`
    with ``y``, ``wfs``, ``positions_m``, the delay and the frame rate; ``s``, ``eps`` and ``config`` are never read)
    (module docstring). ``interaction_matrix`` ``(S, K)`` and ``reconstructor`` ``(K, S)`` replace the file's;
    ``mechanical_coupling``: the DM's Gaussian influence functions' value one pitch away (a record of slopes without
    it assumes :data:`DEFAULT_COUPLING`, in one line); ``command_unit``: what one nm of ``y`` and ``wfs`` is,
    ``"surface"`` (nm of smooth DM surface, eofnn's) or ``"peak"`` (nm at the peak of one actuator's influence
    function, OOPAO's and many RTCs': ``y`` and ``wfs`` are multiplied by the lattice sum of the influence
    functions, :func:`~eofnn.sim.sensing.least_squares.surface_per_command`, and everything identified is in eofnn's
    units); ``seed``: the reference streams'."""
    if command_unit not in COMMAND_UNITS:
        raise TelemetryError(f"command_unit={command_unit!r} is invalid: allowed are {', '.join(COMMAND_UNITS)}")
    from eofnn.sim.grid import ActuatorGrid
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
        centre = positions.mean(0)
        radius = np.linalg.norm(positions - centre, axis=1)
        n_across = int(round(np.ptp(positions, axis=0).max() / pitch)) + 1
        inner = float(radius.min()) - pitch / 2
        obstruction = round(max(0.0, inner) / (n_across * pitch / 2), 3) if inner > pitch else 0.0
        result.grid = {"diameter_m": round(n_across * pitch, 6), "n_across": n_across, "obstruction": obstruction}
        grid_method = "positions: lattice extent and pitch (the nearest eofnn grid)"
        result.warn(f"the actuators are not eofnn's grid: the twin uses {n_across} across at pitch {pitch:.4g} m")
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
    if command_unit == "peak":
        from eofnn.sim.sensing.least_squares import surface_per_command

        scale = surface_per_command(result.mechanical_coupling)
        y_all, wfs_all = y_all * scale, wfs_all * scale
        rec = None if rec is None else rec * scale
        result.warn(f"commands in nm of influence-function peak: y and wfs multiplied by {scale:.4g} (nm of smooth "
                    f"surface per nm of command at coupling {result.mechanical_coupling:g}); all values in eofnn's units")
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
    pol = pol - pol.mean(0)
    parts = _blocks(frames, blocks)

    # The POL carries piston/tip/tilt unless the loop removed them.
    ptt = pol @ _ptt_projector(positions)
    kept = 1 - float(np.mean(ptt.var(0))) / max(float(np.mean(pol.var(0))), 1e-300)
    result.remove_ptt = kept < 0.02

    # Layers.
    lattice = _Lattice(layout)
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
    references = reference_covariances(config, layers, min(frames, REFERENCE_FRAMES), seed=seed)
    cv, seeing = seeing_and_noise(pol, references, positions, pitch)
    fits = [seeing_and_noise(pol[s], references, positions, pitch) for s in parts]
    sensing = ("eofnn's Shack-Hartmann (Fried, Gaussian influence functions of coupling "
               f"{result.mechanical_coupling:g})" if result.sensor == "shack_hartmann" else "the subaperture average")
    method = (f"noise-corrected POL covariance against the twin's ({sensing}) at r0 = {R0_REFERENCE_M} m over "
              f"{2 * min(frames, REFERENCE_FRAMES)} noise-free frames: the structure function (piston, tip, tilt "
              "projected out) over 1.5 pitches to half the pupil scales as r0^(-5/3)")
    e["r0_m"] = Estimate(seeing["r0_m"], _se([f[1]["r0_m"] for f in fits]), "m at 500 nm", method)
    l0s = [f[1]["outer_scale_m"] for f in fits]
    misfit = seeing["misfit"]
    l0_warning = ""
    if len(set(l0s)) > 1 or sorted(misfit.values())[1] < 1.2 * min(misfit.values()):
        l0_warning = (f"L0 not identifiable from this record (pupil {result.grid['diameter_m']:.3g} m, blocks gave "
                      f"{sorted(l0s)} m): the twin keeps the best fit")
        result.warn(l0_warning)
    e["outer_scale_m"] = Estimate(seeing["outer_scale_m"], _se(np.log(l0s)) * seeing["outer_scale_m"], "m",
                                  f"the outer scale of {list(OUTER_SCALES_M)} whose structure function fits best "
                                  f"(rms log misfit {misfit})", l0_warning)

    # WFS noise.
    per_act = np.clip(np.diag(cv), 0, None)
    e["wfs_noise_nm"] = Estimate(math.sqrt(float(per_act.mean())),
                                 _se([math.sqrt(max(float(np.diag(f[0]).mean()), 0)) for f in fits]), "nm",
                                 "white floor of the POL's lagged structure, (4 D(1) - D(2)) / 6, less what the "
                                 "twin's turbulence leaves in it at the identified r0 and winds; RMS over actuators")
    e["wfs_noise_per_actuator_nm"] = Estimate(np.sqrt(per_act).round(4).tolist(), None, "nm", "diagonal of C_v")
    neighbours = layout.neighbours(1.0).numpy()
    corr = cv / np.sqrt(np.outer(per_act, per_act) + 1e-300)
    nearest = [corr[k, j] for k in range(n_act) for j in neighbours[k, 1:] if j < n_act]
    colour = {"nearest_neighbour_correlation": float(np.mean(nearest))}
    colour_method = "off-diagonal of C_v: the mean correlation of nearest neighbours' noise"
    if rec is not None:
        rr = rec @ rec.T
        slope = float(np.sum(cv * rr) / np.sum(rr * rr))
        colour["slope_noise_rms"] = math.sqrt(max(slope, 0))
        colour["model_misfit"] = float(np.linalg.norm(cv - slope * rr) / np.linalg.norm(cv))
        colour_method += "; C_v fitted as sigma² R R^T (slope noise in slope units, white and equal)"
    e["wfs_noise_colour"] = Estimate(colour, None, "", colour_method)
    return result
