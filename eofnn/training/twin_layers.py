"""The frozen-flow layers of a twin identified from telemetry (:func:`identify_layers`, step 6 of
:mod:`eofnn.training.twin`): winds from lagged cross-spectra of the pseudo-open-loop maps, the count chosen by the
record's own consistency over its blocks, with standard errors."""

from __future__ import annotations

import math

import numpy as np

from eofnn.errors import TelemetryError
from eofnn.lazy import lazy_module

torch = lazy_module("torch")

#: Layers whose winds differ by less than this (m/s) are one layer.
MERGE_SPEED_MPS = 2.0
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


class Lattice:
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


def record_blocks(frames: int, blocks: int) -> list[slice]:
    """``blocks`` consecutive slices of equal length over ``frames`` frames (the last frames left over)."""
    size = frames // blocks
    return [slice(i * size, (i + 1) * size) for i in range(blocks)]


def standard_error(values) -> float:
    """The standard error of the mean of ``values`` (NaN for fewer than two)."""
    values = np.asarray(values, dtype=np.float64)
    return float(values.std(ddof=1) / math.sqrt(len(values))) if len(values) > 1 else float("nan")


def _layer_fit(pol_lattice: np.ndarray, lattice: Lattice, period: float, n_layers: int, max_speed: float,
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
            lay[key + "_se"] = standard_error([m[key] for m in near])
        angles = np.radians([m["direction_deg"] for m in near])
        mean = math.atan2(np.sin(angles).mean(), np.cos(angles).mean())
        lay["direction_deg_se"] = math.degrees(standard_error(np.angle(np.exp(1j * (angles - mean)))))
        out.append(lay)
    return out


def _distance(a: dict, b: dict) -> float:
    return math.hypot(a["vx_mps"] - b["vx_mps"], a["vy_mps"] - b["vy_mps"])


def _consistent(lay: dict) -> bool:
    """A layer every block finds again, with the same wind: direction within :data:`CONSISTENT_DIRECTION_DEG`,
    speed within :data:`CONSISTENT_SPEED` (standard errors)."""
    return lay["found_again"] and lay["direction_deg_se"] <= CONSISTENT_DIRECTION_DEG and lay["speed_mps_se"] <= (
        CONSISTENT_SPEED * lay["speed_mps"])


def identify_layers(pol: np.ndarray, lattice: Lattice, period: float, *, max_layers: int = 3,
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
    layers all passed. Each block is fitted with one component more than the record (``n + 1``): a block's greedy
    search that put a component on noise (a shorter record) still has one left for the real layer."""
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
        found = [_merged(_layer_fit(x[part], lattice, period, n + 1, bound, shift)[0])
                 for part in record_blocks(len(x), blocks)]
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
