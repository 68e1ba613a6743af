"""Anti-aliasing prediction inside another simulator's loop, learned from that simulator's truth.

Telemetry holds only the measurement, aliasing and noise included: a predictor fitted on it alone can at best
remove the loop's temporal term (``docs/interop.md``). A simulator also knows its turbulence. The DM's
least-squares fit of the true phase (``sim.turbulence_fit_nm()``) is what the loop should cancel. :func:`run_antialias`
records the simulator's own dithered-integrator loop with that truth beside ``y`` and ``wfs`` (the truth as the
telemetry's ``s``), identifies the plant from the dither, and fits two open-loop EOFs over the same neighbourhood,
from the same frames, with the same ridge search (alpha chosen on each sequence's last ``val_frames``):

- ``eof_measured``: targets cancel the measured pseudo-open-loop values (what telemetry alone can teach);
- ``eof_antialias``: targets cancel the fit of the true phase (``TelemetryDataConfig.target = "s"``, through the
  simulator's own DM gain), while its histories are the same measured, aliased, noisy POL values: a filter wide
  enough in space and time learns to see through the aliasing (Correia & Teixeira 2014 do it with a Wiener
  reconstructor).

Both run as the exported runtime filter (:class:`eofnn.runtime.PredictiveFilter`, POL formed with the identified DM
gain) in the simulator's loop, beside its best-gain integrator (gain scanned on a realisation of its own). The
deployed controller, ``guarded``, is the anti-aliasing EOF if it beat that integrator on the scan realisation,
else the integrator: a whole-loop fallback decided on data it is not scored on. Every contender is scored on the same
``scored_realisations`` realisations (seeds as :func:`eofnn.studies.study.run_study`'s, so the integrator's numbers
are the study's): the residual OPD (median RMS after ``settle_frames``), the fitting error of each realisation,
and the raw contrast at ``separations_lod`` behind a perfect coronagraph (:class:`eofnn.evaluation.contrast.RawContrast`
on the simulator's pupil pixels: fitting error and aliasing are in the speckles).

Beside them (``oracle``, on by default) the oracle (:func:`fit_oracle`): the same open-loop filter trained on the
simulator's truth with more taps, a wider neighbourhood and four times the recorded frames, as eofnn's own contest
builds it (:func:`eofnn.evaluation.contenders.oracle_config`): simulator knowledge, a ceiling and never a contender.
Every predictor is rated against the best classical controller in plain variance, RMS, variance after fitting and
raw contrast against the classical controller best in contrast (:mod:`eofnn.studies.antialias_report`), and by
``eta``, its share of the oracle's variance gain. The classical controllers are built and tuned by
:mod:`eofnn.studies.loop_scans`.

The adapter needs, beyond :class:`~eofnn.interop.loop.SimulatorAdapter`: ``turbulence_fit_nm()``,
``residual_opd_nm()``, ``pupil_mask``, ``dm_gain`` and ``settings["diameter_m"]`` / ``settings["n_subapertures"]``
(:class:`eofnn.interop.oopao.OopaoLoop` has them).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import ClassVar

import numpy as np
import torch

from eofnn.data.history import MAX_HISTORY_LENGTH, HistorySpec, pseudo_open_loop
from eofnn.errors import ConfigError
from eofnn.evaluation.contenders import ORACLE_EXTRA_RADIUS, ORACLE_EXTRA_TAPS, ORACLE_FRAMES_FACTOR, ORACLE_MIN_RADIUS
from eofnn.evaluation.contrast import RawContrast
from eofnn.evaluation.metrics import WelchPSD
from eofnn.interop.loop import (
    FilterControl,
    IntegratorControl,
    TorchControl,
    require_recorded,
    run_closed_loop,
    runtime_filter,
    scan_integrator,
)
from eofnn.studies.antialias_report import ORACLE, antialias_markdown, best_in_contrast, etas, gains
from eofnn.studies.loop_scans import CLASSICAL, PFC_ALPHAS, scan_lqg, scan_modal, scan_pfc
from eofnn.studies.study import ALPHA_PATH
from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry
from eofnn.training.identify import identify_plant
from eofnn.training.task import OptimizationConfig
from eofnn.validation import COUNT, POSITIVE, Constraint, Interval, IsBool, OrNone, check_value, validated

#: What the adapter must offer beyond a SimulatorAdapter.
NEEDED = ("turbulence_fit_nm", "residual_opd_nm", "pupil_mask", "dm_gain", "settings")
CONTENDERS = (*CLASSICAL, "eof_measured", "eof_antialias")

#: The oracle's training frames at least (:data:`eofnn.evaluation.contenders.ORACLE_MIN_FRAMES`'s role, at the loop
#: rate): :data:`ORACLE_FRAMES_FACTOR` times the EOFs' recorded frames, and never fewer than this.
ORACLE_MIN_FRAMES = 8000


@dataclass
@validated
class AntiAliasConfig:
    """Frames, seeds and the filters of :func:`run_antialias` (frames at the loop rate).

    ``train_sequences`` recordings of ``train_frames`` (each its own realisation, the first ``settle_frames``
    dropped), the last ``val_frames`` of each held out to choose the ridge alpha; ``loop_frames``: each tuning run's
    length (the scans and the guard); ``scored_frames``: the frames scored on each scored realisation after its
    ``settle_frames`` (None: ``loop_frames - settle_frames``, as long as a tuning run's); ``radius``: the EOFs'
    neighbourhood (pitches; 2.5: 5 x 5); ``gains``: the integrator's scan; ``oracle``: also train and score the
    oracle (:func:`fit_oracle`), the ceiling each predictor's ``eta`` is a share of.
    """

    train_sequences: int = 3
    train_frames: int = 2000
    val_frames: int = 400
    loop_frames: int = 1000
    scored_frames: int | None = None
    settle_frames: int = 200
    warmup_frames: int = 100
    record_gain: float = 0.25
    dither_nm: float = 10.0
    gains: tuple[float, ...] = (0.15, 0.2, 0.25, 0.3, 0.35, 0.4)
    history_length: int = 4
    radius: float = 2.5
    scored_realisations: int = 3
    wavelength_m: float = 1.65e-6
    separations_lod: tuple[float, ...] = (2.0, 3.0, 5.0)
    contrast_every: int = 10
    psd_segment_frames: int = 128
    seed: int = 0
    oracle: bool = True

    _constraints: ClassVar[dict[str, Constraint]] = {
        **dict.fromkeys(("train_sequences", "train_frames", "loop_frames", "history_length", "scored_realisations",
                         "contrast_every"), COUNT),
        "psd_segment_frames": Interval(8, None, integer=True, unit="frames"),
        **dict.fromkeys(("val_frames", "settle_frames", "warmup_frames"), Interval(0, None, integer=True,
                                                                                  unit="frames")),
        "radius": Interval(0.5, 10, unit="pitches"),
        "wavelength_m": Interval(0, 1e-3, closed="right", unit="m"),
        "dither_nm": Interval(0, 1e5, closed="neither", unit="nm"),
        "scored_frames": OrNone(COUNT),
        "oracle": IsBool(),
    }

    def __post_init__(self) -> None:
        check_value("record_gain", self.record_gain, POSITIVE)
        if self.settle_frames + self.val_frames >= self.train_frames or self.settle_frames >= self.loop_frames:
            raise ConfigError(f"settle_frames={self.settle_frames}, val_frames={self.val_frames} leave nothing of "
                              f"train_frames={self.train_frames} or loop_frames={self.loop_frames} to train or score")
        settled = self.scored_run_frames - self.settle_frames
        if self.psd_segment_frames > settled:
            raise ConfigError(f"psd_segment_frames={self.psd_segment_frames} is longer than the {settled} settled "
                              "frames of a scored run (scored_frames, or loop_frames - settle_frames): at most that")

    @property
    def scored_run_frames(self) -> int:
        """A scored realisation's whole run: ``settle_frames`` then ``scored_frames``."""
        return self.loop_frames if self.scored_frames is None else self.settle_frames + self.scored_frames


class PupilContrast:
    """An observer of :func:`~eofnn.interop.loop.run_closed_loop`: the raw contrast of the simulator's residual OPD
    over its pupil pixels, every ``every``-th frame from ``settle_frames`` on (4 focal-plane pixels per lambda/D,
    out to the DM's control radius ``n_subapertures / 2`` lambda/D)."""

    def __init__(self, sim, wavelength_m: float, settle_frames: int, every: int) -> None:
        mask = np.asarray(sim.pupil_mask, dtype=bool)
        res = mask.shape[0]
        pixels = _PixelGrid(res, sim.settings["diameter_m"] / res, np.argwhere(np.ones_like(mask)))
        self.contrast = RawContrast(pixels, wavelength_m, every=every, pupil=mask.ravel(),
                                    pupil_diameter_m=sim.settings["diameter_m"],
                                    control_radius_lod=sim.settings["n_subapertures"] / 2)
        self.settle, self.every = settle_frames, every

    def __call__(self, n: int, sim) -> None:
        if n >= self.settle and n % self.every == 0:
            self.contrast.add(torch.from_numpy(np.asarray(sim.residual_opd_nm(), dtype=np.float64))[None])


@dataclass(frozen=True)
class _PixelGrid:
    """The simulator's square pixel grid as :class:`~eofnn.evaluation.contrast.RawContrast` reads a grid."""

    n_across: int
    pitch_m: float
    indices: np.ndarray


def record_with_truth(sim, config: AntiAliasConfig, count: int | None = None, first: int = 0) -> list:
    """``count`` (unset: ``train_sequences``) dithered-integrator recordings, each as telemetry with the simulator's
    truth as ``s`` (the first ``settle_frames`` dropped); ``first``: the index of the first (its seeds follow on from
    the ``first`` recordings made before)."""
    c, sequences = config, []
    for i in range(first, first + (c.train_sequences if count is None else count)):
        truth: list[np.ndarray] = []

        def observe(n: int, simulator, truth=truth) -> None:
            truth.append(np.asarray(simulator.turbulence_fit_nm()))

        record = require_recorded(run_closed_loop(
            sim, IntegratorControl(c.record_gain, c.dither_nm, seed=c.seed + 140 + i), c.train_frames,
            c.seed + 40 + i, observers=[observe]), c.record_gain, sim)
        sequences.append(replace(record.telemetry(start=c.settle_frames),
                                 s=torch.from_numpy(np.stack(truth[c.settle_frames:]))))
    return sequences


def run_antialias(sim, config: AntiAliasConfig | None = None, external: dict | None = None,
                  progress: Callable[[str], None] | None = None) -> dict:
    """Record with truth, fit the two EOFs, tune the integrator, guard, and score every contender in ``sim``'s loop
    (module docstring); returns the JSON of ``metrics.json``. ``external``: more predictors trained elsewhere, by
    name, each ``build(sim, plant) -> (PredictiveFilter, info)`` given the plant identified from the recording
    (:mod:`eofnn.studies.transfer`: one trained in eofnn's own simulation), scored beside the others. ``progress``:
    told each stage as it ends (a line of text), for a long run's log."""
    from eofnn.interop.oopao import fitting_error

    c = config or AntiAliasConfig()
    missing = [name for name in NEEDED if not hasattr(sim, name)]
    if missing:
        raise ConfigError(f"{type(sim).__name__} lacks {', '.join(missing)}: anti-aliasing training needs the "
                          "simulator's truth and pupil (eofnn.interop.oopao.OopaoLoop has them)")
    say = progress or (lambda text: None)
    telemetry = record_with_truth(sim, c)
    plant = identify_plant(telemetry)
    plant.require_identified()
    say(f"recorded {len(telemetry)} sequences, plant identified")
    filters, fits = fit_eofs(sim, telemetry, plant, c)
    say("EOFs fitted")
    if c.oracle:
        filters[ORACLE], fits[ORACLE] = fit_oracle(sim, telemetry, plant, c)
        say(f"oracle fitted on {fits[ORACLE]['sequences']} recordings")
    conditions = {}
    for name, build in (external or {}).items():
        filters[name], fits[name] = build(sim, plant)
        conditions[name] = fits[name].pop("conditions", None)  # what it was trained in: the loop warns on a shift
    scan_seed = c.seed + 3
    scan = scan_integrator(sim, c.gains, c.loop_frames, scan_seed, c.settle_frames)
    pol = torch.stack([pseudo_open_loop(seq.wfs, seq.y, plant.dm_gain) for seq in telemetry])
    modal = scan_modal(sim, pol, plant.dm_gain, c, scan_seed)
    lqg = scan_lqg(sim, pol, plant.dm_gain, c, scan_seed)
    say("integrator, modal integrator and LQG tuned")
    pfc = scan_pfc(sim, pol, plant, c, scan_seed)
    say("PFC tuned")

    def control(name: str):
        if name == "integrator":
            return IntegratorControl(scan["gain"])
        if name == "modal":
            return TorchControl(modal["controller"], sim.delay_frames)
        if name == "lqg":
            return TorchControl(lqg["controller"], sim.delay_frames)
        if name == "pfc":
            return pfc["controller"]
        return FilterControl(filters[name], scan["gain"], c.warmup_frames, conditions=conditions.get(name))

    guard = run_closed_loop(sim, control("eof_antialias"), c.loop_frames, scan_seed).metrics(c.settle_frames)
    deployed = "eof_antialias" if guard.median_rms_nm is not None and guard.median_rms_nm < scan["median_rms_nm"] \
        else "integrator"
    scored = [c.seed + 2, *(c.seed + 20 + i for i in range(c.scored_realisations - 1))]
    names = (*CONTENDERS, *(external or {}), *((ORACLE,) if c.oracle else ()))
    results = {}
    for name in names:
        results[name] = score(sim, control, name, scored, c)
        say(f"{name} scored: {results[name]['mean_of_realisations_nm']} nm")
    results["guarded"] = {**results[deployed], "deployed": deployed}
    fitting = [fitting_error(sim, c.scored_run_frames, seed, start=c.settle_frames)["median_rms_nm"] for seed in scored]
    # The best classical controller is chosen on the scan realisation, as each was tuned: not on the scored ones.
    on_scan = {"integrator": scan["median_rms_nm"], "modal": modal["median_rms_nm"], "lqg": lqg["median_rms_nm"],
               "pfc": pfc["median_rms_nm"]}
    best = min((name for name, v in on_scan.items() if v is not None), key=on_scan.get)
    scored_best = _best_scored(results)  # the strongest on the realisations scored: the referee's baseline
    return {"simulator": sim.describe(), "config": asdict(c), "scored_seeds": scored,
            "identified": {"dm_gain": plant.dm_gain, "wfs_noise_nm": plant.wfs_noise_nm, "dm_gain_true": sim.dm_gain},
            "fits": fits, "integrator_scan": {"gain": scan["gain"], "scan": {str(g): v for g, v in scan["scan"].items()}},
            "modal_scan": {key: modal[key] for key in ("gain_margin", "median_rms_nm", "scan", "info")},
            "lqg_scan": {key: lqg[key] for key in ("ar_order", "noise_scale", "noise_covariance", "median_rms_nm", "scan")},
            "pfc_scan": {"alpha": pfc["alpha"], "aliases": pfc["aliases"], "noise_covariance": pfc["noise_covariance"],
                         "median_rms_nm": pfc["median_rms_nm"],
                         "scan": pfc["scan"], "identified": pfc["info"]},
            "guard": {"scan_integrator_nm": scan["median_rms_nm"], "scan_eof_antialias_nm": guard.median_rms_nm,
                      "deployed": deployed},
            "fitting_error_nm": fitting, "contenders": results, "best_classical": best,
            "roles": {name: "classical" if name in CLASSICAL else "oracle" if name == ORACLE else "predictor"
                      for name in results},
            "psd_frequency_hz": np.fft.rfftfreq(c.psd_segment_frames, 1 / sim.frame_rate_hz).tolist(),
            "frozen_flow_hz": frozen_flow_hz(sim),
            "gains": gains(results, fitting, c.separations_lod, "integrator"),
            "gains_over_best_classical": gains(results, fitting, c.separations_lod, best,
                                               best_in_contrast(results, c.separations_lod)),
            "best_classical_on_scored": scored_best,
            "gains_over_best_classical_on_scored": None if scored_best is None else gains(
                results, fitting, c.separations_lod, scored_best, best_in_contrast(results, c.separations_lod)),
            "eta": etas(results, best) if c.oracle else None,
            "eta_over_best_classical_on_scored": etas(results, scored_best) if c.oracle and scored_best else None}


def fit_eofs(sim, telemetry: list, plant, c: AntiAliasConfig) -> tuple[dict, dict]:
    """The two open-loop EOFs of :func:`run_antialias` fitted on ``telemetry`` (:func:`record_with_truth`) through
    ``plant`` (identified from it): ``({name: runtime filter}, {name: {"alpha", "target"}})``."""
    spec = HistorySpec("open_loop", c.history_length, sim.delay_frames)
    network = {"class_path": "eofnn.models.linear.LinearFilter",
               "init_args": {"structure": "neighbourhood", "radius": c.radius}}
    optimization = OptimizationConfig(alpha="auto", alpha_path=ALPHA_PATH)
    filters, fits = {}, {}
    for name, target in (("eof_measured", "measured"), ("eof_antialias", "s")):
        data = TelemetryDataConfig(val_frames=c.val_frames, seed=c.seed, target=target,
                                   target_dm_gain=sim.dm_gain if target == "s" else None)
        fitted = fit_from_telemetry(telemetry, spec, network, plant=plant, data=data, optimization=optimization)
        filters[name] = runtime_filter(fitted.network, spec, plant.dm_gain)
        fits[name] = {"alpha": fitted.info.get("alpha"), "target": target}
    return filters, fits


def oracle_reach(c: AntiAliasConfig) -> dict:
    """The oracle's reach beyond the anti-aliasing EOF's, as eofnn's own contest sets it
    (:func:`eofnn.evaluation.contenders.oracle_config`): :data:`~eofnn.evaluation.contenders.ORACLE_EXTRA_TAPS` more
    taps, a neighbourhood :data:`~eofnn.evaluation.contenders.ORACLE_EXTRA_RADIUS` pitch wider (at least
    :data:`~eofnn.evaluation.contenders.ORACLE_MIN_RADIUS`), and :data:`ORACLE_FRAMES_FACTOR` times the recorded
    frames (at least :data:`ORACLE_MIN_FRAMES`) in whole recordings of ``train_frames``, the EOFs' among them:
    ``{"history_length", "radius", "sequences", "val_frames"}`` (``val_frames`` of each held out for its ridge alpha,
    at least an eighth of what each keeps)."""
    frames = max(ORACLE_FRAMES_FACTOR * c.train_sequences * c.train_frames, ORACLE_MIN_FRAMES)
    kept = c.train_frames - c.settle_frames
    return {"history_length": min(c.history_length + ORACLE_EXTRA_TAPS, MAX_HISTORY_LENGTH),
            "radius": max(c.radius + ORACLE_EXTRA_RADIUS, ORACLE_MIN_RADIUS),
            "sequences": max(math.ceil(frames / c.train_frames), c.train_sequences),
            "val_frames": min(max(c.val_frames, kept // 8), kept - 1)}


def fit_oracle(sim, telemetry: list, plant, c: AntiAliasConfig) -> tuple:
    """The oracle of :func:`run_antialias`: the least-squares open-loop filter fitted on the simulator's truth (the
    DM's fit of the true phase, as ``eof_antialias``'s target) with more reach than any contender
    (:func:`oracle_reach`): the recordings ``telemetry`` and as many more as it needs, recorded in the same loop on
    realisations of their own. Its inputs are the measured POL histories through ``plant`` (identified from
    ``telemetry``), as every contender's are. Knowledge no telescope has: a ceiling on linear prediction from these
    inputs, never a contender. ``(runtime filter, {"alpha", "target", "knowledge", reach...})``."""
    reach = oracle_reach(c)
    more = record_with_truth(sim, c, count=reach["sequences"] - len(telemetry), first=len(telemetry))
    spec = HistorySpec("open_loop", reach["history_length"], sim.delay_frames)
    network = {"class_path": "eofnn.models.linear.LinearFilter",
               "init_args": {"structure": "neighbourhood", "radius": reach["radius"]}}
    # Batches of 256 frames: its normal equations and features are the largest of the study (7 x 7 x 6 at 40 x 40).
    data = TelemetryDataConfig(batch_frames=256, val_frames=reach["val_frames"], seed=c.seed, target="s",
                               target_dm_gain=sim.dm_gain)
    fitted = fit_from_telemetry([*telemetry, *more], spec, network, plant=plant, data=data,
                                optimization=OptimizationConfig(alpha="auto", alpha_path=ALPHA_PATH))
    return runtime_filter(fitted.network, spec, plant.dm_gain), {
        "alpha": fitted.info.get("alpha"), "target": "s", "knowledge": ORACLE_KNOWLEDGE, **reach,
        "train_frames": reach["sequences"] * c.train_frames}


#: What the oracle knows that no telescope does (said beside its numbers).
ORACLE_KNOWLEDGE = ("trained on the simulator's truth (the DM's least-squares fit of the true phase, the target the "
                    "loop must cancel), on more recordings and with more taps and a wider neighbourhood than any "
                    "contender: simulator knowledge, a ceiling on linear prediction from the measured POL histories, "
                    "not a contender")


def _best_scored(results: dict) -> str | None:
    """The classical controller of least mean residual over the scored realisations (``None``: none held)."""
    held = [n for n in CLASSICAL if n in results and results[n]["mean_of_realisations_nm"] is not None]
    return min(held, key=lambda n: results[n]["mean_of_realisations_nm"]) if held else None


def frozen_flow_hz(sim) -> float:
    """``v / (2 pitch)``: the highest temporal frequency frozen flow puts on the DM's modes (Hz)."""
    s = sim.settings
    return float(s["wind_speed_mps"] / (2 * s["diameter_m"] / s["n_subapertures"]))


def score(sim, control, name: str, seeds: list[int], c: AntiAliasConfig) -> dict:
    """One contender on every scored realisation: median RMS (None if it diverged), raw contrast, and the temporal
    PSD of the measured residual (``wfs`` on the actuators, in the loop's command units; averaged over actuators,
    segments and the realisations that did not diverge)."""
    medians, contrasts, shift = [], [], []
    psd = WelchPSD(c.psd_segment_frames, sim.frame_rate_hz, c.settle_frames)
    # Whole segments of each run: what is left over would be joined to the next realisation's frames.
    end = c.settle_frames + (c.scored_run_frames - c.settle_frames) // c.psd_segment_frames * c.psd_segment_frames
    for seed in seeds:
        observer = PupilContrast(sim, c.wavelength_m, c.settle_frames, c.contrast_every)
        record = run_closed_loop(sim, control(name), c.scored_run_frames, seed, observers=[observer])
        shift = shift or record.shift
        medians.append(record.metrics(c.settle_frames).median_rms_nm)
        contrasts.append(observer.contrast.at(c.separations_lod) if record.diverged_frame is None else None)
        if record.diverged_frame is None:
            psd(0, {"eps": torch.from_numpy(record.wfs[:end])[None]})
    finite = None not in medians
    return {"realisations_median_rms_nm": medians, "shift": shift, "measured_psd_nm2_per_hz": psd.result()[1],
            "mean_of_realisations_nm": float(np.mean(medians)) if finite else None,
            "realisations_contrast": contrasts,
            "mean_contrast": {s: None if contrasts[0][s] is None else float(np.mean([cs[s] for cs in contrasts]))
                              for s in contrasts[0]} if finite else None}


# The report's and the classical scans' names, where callers found them before the module was split.
__all__ = ["CLASSICAL", "CONTENDERS", "NEEDED", "ORACLE", "ORACLE_KNOWLEDGE", "PFC_ALPHAS", "AntiAliasConfig",
           "PupilContrast", "antialias_markdown", "best_in_contrast", "etas", "fit_eofs", "fit_oracle",
           "frozen_flow_hz", "gains", "oracle_reach", "record_with_truth", "run_antialias", "scan_lqg", "scan_modal",
           "scan_pfc", "score"]
