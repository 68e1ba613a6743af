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

The adapter needs, beyond :class:`~eofnn.interop.loop.SimulatorAdapter`: ``turbulence_fit_nm()``,
``residual_opd_nm()``, ``pupil_mask``, ``dm_gain`` and ``settings["diameter_m"]`` / ``settings["n_subapertures"]``
(:class:`eofnn.interop.oopao.OopaoLoop` has them).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import ClassVar

import numpy as np
import torch

from eofnn.control.classical import ModalIntegrator
from eofnn.control.modal import GAIN_MARGIN_CANDIDATES, lqg_from_pol, modal_statistics, optimal_gains
from eofnn.data.history import HistorySpec, pseudo_open_loop
from eofnn.errors import ConfigError
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
from eofnn.sim.layout import ActuatorLayout, layout_from_positions
from eofnn.studies.report import psd_bands_markdown
from eofnn.studies.study import ALPHA_PATH
from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry
from eofnn.training.identify import identify_plant
from eofnn.training.task import OptimizationConfig
from eofnn.validation import COUNT, POSITIVE, Constraint, Interval, check_value, validated

#: What the adapter must offer beyond a SimulatorAdapter.
NEEDED = ("turbulence_fit_nm", "residual_opd_nm", "pupil_mask", "dm_gain", "settings")
CONTENDERS = ("integrator", "modal", "lqg", "pfc", "eof_measured", "eof_antialias")
CLASSICAL = ("integrator", "modal", "lqg", "pfc")


@dataclass
@validated
class AntiAliasConfig:
    """Frames, seeds and the filters of :func:`run_antialias` (frames at the loop rate).

    ``train_sequences`` recordings of ``train_frames`` (each its own realisation, the first ``settle_frames``
    dropped), the last ``val_frames`` of each held out to choose the ridge alpha; ``radius``: the EOFs'
    neighbourhood (pitches; 2.5: 5 x 5); ``gains``: the integrator's scan.
    """

    train_sequences: int = 3
    train_frames: int = 2000
    val_frames: int = 400
    loop_frames: int = 1000
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

    _constraints: ClassVar[dict[str, Constraint]] = {
        **dict.fromkeys(("train_sequences", "train_frames", "loop_frames", "history_length", "scored_realisations",
                         "contrast_every"), COUNT),
        "psd_segment_frames": Interval(8, None, integer=True, unit="frames"),
        **dict.fromkeys(("val_frames", "settle_frames", "warmup_frames"), Interval(0, None, integer=True,
                                                                                  unit="frames")),
        "radius": Interval(0.5, 10, unit="pitches"),
        "wavelength_m": Interval(0, 1e-3, closed="right", unit="m"),
        "dither_nm": Interval(0, 1e5, closed="neither", unit="nm"),
    }

    def __post_init__(self) -> None:
        check_value("record_gain", self.record_gain, POSITIVE)
        if self.settle_frames + self.val_frames >= self.train_frames or self.settle_frames >= self.loop_frames:
            raise ConfigError(f"settle_frames={self.settle_frames}, val_frames={self.val_frames} leave nothing of "
                              f"train_frames={self.train_frames} or loop_frames={self.loop_frames} to train or score")
        settled = self.loop_frames - self.settle_frames
        if self.psd_segment_frames > settled:
            raise ConfigError(f"psd_segment_frames={self.psd_segment_frames} is longer than the {settled} settled "
                              "frames of a scored run (loop_frames - settle_frames): at most that")


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


def record_with_truth(sim, config: AntiAliasConfig) -> list:
    """``train_sequences`` dithered-integrator recordings, each as telemetry with the simulator's truth as ``s``
    (the first ``settle_frames`` dropped)."""
    c, sequences = config, []
    for i in range(c.train_sequences):
        truth: list[np.ndarray] = []

        def observe(n: int, simulator, truth=truth) -> None:
            truth.append(np.asarray(simulator.turbulence_fit_nm()))

        record = require_recorded(run_closed_loop(
            sim, IntegratorControl(c.record_gain, c.dither_nm, seed=c.seed + 140 + i), c.train_frames,
            c.seed + 40 + i, observers=[observe]), c.record_gain, sim)
        sequences.append(replace(record.telemetry(start=c.settle_frames),
                                 s=torch.from_numpy(np.stack(truth[c.settle_frames:]))))
    return sequences


def run_antialias(sim, config: AntiAliasConfig | None = None, external: dict | None = None) -> dict:
    """Record with truth, fit the two EOFs, tune the integrator, guard, and score every contender in ``sim``'s loop
    (module docstring); returns the JSON of ``metrics.json``. ``external``: more predictors trained elsewhere, by
    name, each ``build(sim, plant) -> (PredictiveFilter, info)`` given the plant identified from the recording
    (:mod:`eofnn.studies.transfer`: one trained in eofnn's own simulation), scored beside the others."""
    from eofnn.interop.oopao import fitting_error

    c = config or AntiAliasConfig()
    missing = [name for name in NEEDED if not hasattr(sim, name)]
    if missing:
        raise ConfigError(f"{type(sim).__name__} lacks {', '.join(missing)}: anti-aliasing training needs the "
                          "simulator's truth and pupil (eofnn.interop.oopao.OopaoLoop has them)")
    telemetry = record_with_truth(sim, c)
    plant = identify_plant(telemetry)
    plant.require_identified()
    filters, fits = fit_eofs(sim, telemetry, plant, c)
    conditions = {}
    for name, build in (external or {}).items():
        filters[name], fits[name] = build(sim, plant)
        conditions[name] = fits[name].pop("conditions", None)  # what it was trained in: the loop warns on a shift
    scan_seed = c.seed + 3
    scan = scan_integrator(sim, c.gains, c.loop_frames, scan_seed, c.settle_frames)
    pol = torch.stack([pseudo_open_loop(seq.wfs, seq.y, plant.dm_gain) for seq in telemetry])
    modal = scan_modal(sim, pol, plant.dm_gain, c, scan_seed)
    lqg = scan_lqg(sim, pol, plant.dm_gain, c, scan_seed)
    pfc = scan_pfc(sim, pol, plant, c, scan_seed)

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
    results = {name: score(sim, control, name, scored, c) for name in (*CONTENDERS, *(external or {}))}
    results["guarded"] = {**results[deployed], "deployed": deployed}
    fitting = [fitting_error(sim, c.loop_frames, seed, start=c.settle_frames)["median_rms_nm"] for seed in scored]
    # The best classical controller is chosen on the scan realisation, as each was tuned: not on the scored ones.
    on_scan = {"integrator": scan["median_rms_nm"], "modal": modal["median_rms_nm"], "lqg": lqg["median_rms_nm"],
               "pfc": pfc["median_rms_nm"]}
    best = min((name for name, v in on_scan.items() if v is not None), key=on_scan.get)
    return {"simulator": sim.describe(), "config": asdict(c), "scored_seeds": scored,
            "identified": {"dm_gain": plant.dm_gain, "wfs_noise_nm": plant.wfs_noise_nm, "dm_gain_true": sim.dm_gain},
            "fits": fits, "integrator_scan": {"gain": scan["gain"], "scan": {str(g): v for g, v in scan["scan"].items()}},
            "modal_scan": {key: modal[key] for key in ("gain_margin", "median_rms_nm", "scan", "info")},
            "lqg_scan": {"ar_order": lqg["ar_order"], "scan": lqg["scan"]},
            "pfc_scan": {"alpha": pfc["alpha"], "aliases": pfc["aliases"], "noise_covariance": pfc["noise_covariance"],
                         "median_rms_nm": pfc["median_rms_nm"],
                         "scan": pfc["scan"], "identified": pfc["info"]},
            "guard": {"scan_integrator_nm": scan["median_rms_nm"], "scan_eof_antialias_nm": guard.median_rms_nm,
                      "deployed": deployed},
            "fitting_error_nm": fitting, "contenders": results, "best_classical": best,
            "psd_frequency_hz": np.fft.rfftfreq(c.psd_segment_frames, 1 / sim.frame_rate_hz).tolist(),
            "frozen_flow_hz": frozen_flow_hz(sim),
            "gains": gains(results, fitting, c.separations_lod, "integrator"),
            "gains_over_best_classical": gains(results, fitting, c.separations_lod, best,
                                               best_in_contrast(results, c.separations_lod))}


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


def _grid_indices(sim) -> torch.Tensor | None:
    """``(K, 2)`` lattice rows and columns of ``sim``'s actuators (``None`` off a lattice): the KL modes' homogenised
    covariance (:func:`eofnn.control.modal.modal_statistics`)."""
    layout = layout_from_positions(sim.positions_m)
    indices = layout.lattice_indices if isinstance(layout, ActuatorLayout) else layout.indices
    return None if indices is None else torch.as_tensor(indices)


def scan_modal(sim, pol: torch.Tensor, dm_gain: float, c: AntiAliasConfig, seed: int) -> dict:
    """The modal integrator with optimised gains (Gendron & Léna 1994, :func:`eofnn.control.modal.optimal_gains`)
    built from the recorded telemetry's ``(R, T, K)`` POL values (formed with the identified DM gain): KL modes, each
    mode's temporal PSD and noise, one gain per mode minimising its predicted residual, and how near its critical gain
    a mode may go (:data:`~eofnn.control.modal.GAIN_MARGIN_CANDIDATES`) chosen in the loop on the scan realisation
    ``seed``, as eofnn's own loop chooses it: ``{"controller", "gain_margin", "median_rms_nm", "scan", "info"}``."""
    stats = modal_statistics(pol, grid_indices=_grid_indices(sim))
    built, critical = {}, None
    for margin in GAIN_MARGIN_CANDIDATES:
        gains, _, critical = optimal_gains(stats, sim.delay_frames, dm_gain, min_gain_margin=margin)
        built[margin] = ModalIntegrator(stats.modes, gains, sim.delay_frames, dm_gain)
    margin, rms, scan = _best_in_loop(sim, {m: TorchControl(ctrl, sim.delay_frames) for m, ctrl in built.items()},
                                      c, seed, fallback=GAIN_MARGIN_CANDIDATES[-1])
    gains = built[margin].gains
    quantiles = gains.quantile(torch.tensor([0.0, 0.1, 0.5, 0.9, 1.0], dtype=gains.dtype))
    return {"controller": built[margin], "gain_margin": margin, "median_rms_nm": rms, "scan": scan,
            "info": {"critical_gain": critical, "gains_quantiles_0_10_50_90_100": [round(float(q), 4) for q in quantiles],
                     "noise_rms_nm_median": float(stats.noise_variance.median().sqrt())}}


def scan_lqg(sim, pol: torch.Tensor, dm_gain: float, c: AntiAliasConfig, seed: int) -> dict:
    """The LQG (:func:`eofnn.control.modal.lqg_from_pol`: AR model per KL mode, stationary Kalman filter) built
    from the recorded telemetry's ``(R, T, K)`` POL values (formed with the identified DM gain), its AR order (1 or
    2) chosen in the loop on the scan realisation ``seed``: ``{"controller", "ar_order", "median_rms_nm", "scan"}``."""
    grid_indices = _grid_indices(sim)
    built = {order: lqg_from_pol(pol, sim.delay_frames, dm_gain, order, grid_indices=grid_indices)
             for order in (1, 2)}
    order, rms, scan = _best_in_loop(sim, {order: TorchControl(lqg, sim.delay_frames) for order, lqg in built.items()},
                                     c, seed, fallback=2)
    return {"controller": built[order], "ar_order": order, "median_rms_nm": rms, "scan": scan}


#: The frozen-flow memories (:attr:`eofnn.control.config.PfcConfig.alpha`) predictive Fourier control's scan tries:
#: new turbulence enters a finite pupil, so a Fourier mode forgets its past within about a pupil crossing (``D / v``:
#: 100 frames for 2 m at 20 m/s and 1 kHz, 400 for 8 m), and the default 0.9999 trusts it far longer (the scan that
#: chose this grid: ``docs/findings.md``).
PFC_ALPHAS = (0.98, 0.99, 0.995, 0.998)


def scan_pfc(sim, pol: torch.Tensor, plant, c: AntiAliasConfig, seed: int) -> dict:
    """Predictive Fourier control (:func:`eofnn.studies.pfc.pfc_in_loop`: a Kalman filter per Fourier mode, the
    winds, noise and per-mode variances from the recorded telemetry's ``(R, T, K)`` POL values) tuned in the loop on
    the scan realisation ``seed``, as the integrator's gain and the LQG's AR order are: its memory ``alpha`` over
    :data:`PFC_ALPHAS` without aliases in its state, on past the grid's edge while the best is there
    (:func:`~eofnn.control.config.alpha_past_edge`), then one ring of aliases at the chosen alpha, then (where the
    loop exposes its reconstructor) the noise coloured by it, ``R R^T``, at the chosen alpha and aliases:
    ``{"controller", "alpha", "aliases", "noise_covariance", "median_rms_nm", "scan", "info"}``."""
    from eofnn.control.config import PfcConfig, alpha_past_edge
    from eofnn.studies.pfc import pfc_in_loop

    def build(aliases: int, alpha: float, noise: str = "white"):
        return pfc_in_loop(sim, pol, plant.dm_gain, plant.wfs_noise_nm,
                           PfcConfig(aliases=aliases, alpha=alpha, noise_covariance=noise))

    built = {alpha: build(0, alpha) for alpha in PFC_ALPHAS}
    alpha, rms, scan = _best_in_loop(sim, built, c, seed, fallback=PFC_ALPHAS[-1])
    tried = {float(key): v for key, v in scan.items()}
    # On past the grid's edge while the best is there, as the integrator's gain scan climbs.
    while (extra := alpha_past_edge(tried, len(tried) - len(PFC_ALPHAS))) is not None:
        built[extra] = build(0, extra)
        tried[extra] = run_closed_loop(sim, built[extra], c.loop_frames, seed).metrics(c.settle_frames).median_rms_nm
        stable = {a: v for a, v in tried.items() if v is not None}
        alpha = min(stable, key=stable.get) if stable else alpha
        rms = stable.get(alpha)
    scan = {f"aliases=0, alpha={key}": v for key, v in tried.items()}
    with_ring = build(1, alpha)
    ring = run_closed_loop(sim, with_ring, c.loop_frames, seed).metrics(c.settle_frames).median_rms_nm
    scan[f"aliases=1, alpha={alpha:g}"] = ring
    aliases = 1 if ring is not None and (rms is None or ring < rms) else 0
    controller, rms = (with_ring, ring) if aliases else (built[alpha], rms)
    noise = "white"
    if getattr(sim, "reconstructor", None) is not None:
        coloured = build(aliases, alpha, "reconstructor")
        coloured_rms = run_closed_loop(sim, coloured, c.loop_frames, seed).metrics(c.settle_frames).median_rms_nm
        scan[f"aliases={aliases}, alpha={alpha:g}, noise=reconstructor"] = coloured_rms
        if coloured_rms is not None and (rms is None or coloured_rms < rms):
            controller, rms, noise = coloured, coloured_rms, "reconstructor"
    info = controller.controller.info or {}
    return {"controller": controller, "alpha": alpha, "aliases": aliases, "noise_covariance": noise,
            "median_rms_nm": rms, "scan": scan,
            "info": {"layers": info.get("layers"), "noise_rms_nm": info.get("noise_rms_nm")}}


def _best_in_loop(sim, controls: dict, c: AntiAliasConfig, seed: int, fallback):
    """Each of ``controls`` (by setting) closed in ``sim``'s loop on the realisation ``seed``: ``(the setting with the
    lowest median RMS, that RMS, {str(setting): RMS or None if it diverged})``; ``fallback`` and ``None`` when every
    one diverged."""
    scan = {setting: run_closed_loop(sim, control, c.loop_frames, seed).metrics(c.settle_frames).median_rms_nm
            for setting, control in controls.items()}
    stable = {setting: v for setting, v in scan.items() if v is not None}
    best = min(stable, key=stable.get) if stable else fallback
    return best, stable.get(best), {str(setting): v for setting, v in scan.items()}


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
    end = c.settle_frames + (c.loop_frames - c.settle_frames) // c.psd_segment_frames * c.psd_segment_frames
    for seed in seeds:
        observer = PupilContrast(sim, c.wavelength_m, c.settle_frames, c.contrast_every)
        record = run_closed_loop(sim, control(name), c.loop_frames, seed, observers=[observer])
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


def best_in_contrast(results: dict, separations: tuple[float, ...]) -> dict[str, str | None]:
    """Per separation (``"3"``), the classical controller of least mean raw contrast there (``None`` where none held
    the loop with a contrast): the baseline a contrast gain is taken against, not the one best in variance."""
    out = {}
    for s in (f"{s:g}" for s in separations):
        have = [n for n in CLASSICAL if n in results and (results[n]["mean_contrast"] or {}).get(s) is not None]
        out[s] = min(have, key=lambda n: results[n]["mean_contrast"][s]) if have else None
    return out


def gains(results: dict, fitting: list[float], separations: tuple[float, ...], against: str,
          contrast_against: dict[str, str | None] | None = None) -> dict:
    """Each predictor against the classical controller ``against``: the plain variance (median RMS squared, summed
    over realisations) and RMS ratios, the variance after fitting (each realisation's fitting error subtracted in
    quadrature, summed over realisations) and mean raw contrast, as classical over predictor (above 1: the predictor
    is better), and the paired RMS differences. ``contrast_against``: per separation, the controller the contrast is
    compared with (:func:`best_in_contrast`; said in ``contrast_against``); unset, ``against``."""
    out = {}
    for name in (n for n in results if n not in CLASSICAL):
        base, mine = results[against], results[name]
        if mine["mean_of_realisations_nm"] is None or base["mean_of_realisations_nm"] is None:  # one diverged
            out[name] = None
            continue
        var = [sum(r * r - f * f for r, f in zip(run["realisations_median_rms_nm"], fitting, strict=True))
               for run in (base, mine)]
        plain = [sum(r * r for r in run["realisations_median_rms_nm"]) for run in (base, mine)]
        contrast, used = {}, {}
        for s in (f"{s:g}" for s in separations):
            other = results.get((contrast_against or {}).get(s) or against)
            if other is None or other["mean_contrast"] is None or other["mean_contrast"].get(s) is None:
                continue
            contrast[s] = other["mean_contrast"][s] / mine["mean_contrast"][s]
            used[s] = (contrast_against or {}).get(s) or against
        out[name] = {"variance": plain[0] / plain[1],
                     "rms": base["mean_of_realisations_nm"] / mine["mean_of_realisations_nm"],
                     "variance_after_fitting": var[0] / var[1],
                     "contrast": contrast, "contrast_against": used,
                     "paired_difference_nm": [a - b for a, b in zip(base["realisations_median_rms_nm"],
                                                                    mine["realisations_median_rms_nm"], strict=True)]}
    return out


def antialias_markdown(metrics: dict) -> str:
    """``results.md`` of :func:`run_antialias`: per contender the residual per realisation, its mean and the raw
    contrast, then the gains over the integrator."""
    def nm(value):
        return "diverged" if value is None else f"{value:.1f}"

    seps = [f"{s:g}" for s in metrics["config"]["separations_lod"]]
    fit = metrics["fitting_error_nm"]
    lines = [f"# Anti-aliasing EOF inside {metrics['simulator']['simulator']}", "", f"`{metrics.get('command', '')}`", "",
             f"Fitting error per realisation: {', '.join(f'{v:.1f}' for v in fit)} nm. Integrator gain "
             f"{metrics['integrator_scan']['gain']} (scanned); deployed by the guard: {metrics['guard']['deployed']}.",
             "", "| contender | residual per realisation (nm) | mean (nm) | "
             + " | ".join(f"raw contrast at {s} λ/D" for s in seps) + " |", "|---|---|---|" + "---|" * len(seps)]
    for name, run in metrics["contenders"].items():
        contrast = run["mean_contrast"] or {}
        lines.append(f"| {name} | {', '.join(nm(v) for v in run['realisations_median_rms_nm'])} | "
                     f"{nm(run['mean_of_realisations_nm'])} | "
                     + " | ".join("" if contrast.get(s) is None else f"{contrast[s]:.2e}" for s in seps) + " |")
    lines += psd_bands_markdown(metrics)
    lqg, pfc = metrics["lqg_scan"], metrics.get("pfc_scan")
    winds = "" if not pfc else f" PFC: alpha {pfc.get('alpha', 0.9999):g}, {pfc['aliases']} ring(s) of aliases, " \
        f"{pfc.get('noise_covariance', 'white')} noise " \
        f"(scan: {pfc['scan']}), layers " + ", ".join(
        f"{lay['speed_mps']:.1f} m/s at {lay['direction_deg']:.0f}° ({lay['weight']:.0%})"
        for lay in pfc["identified"]["layers"] or []) + " identified from the telemetry."
    modal = metrics.get("modal_scan")
    gains_line = "" if not modal else f" Modal integrator (optimised gains): gain margin {modal['gain_margin']:g} " \
        f"(scan: {modal['scan']}), gains {modal['info']['gains_quantiles_0_10_50_90_100']} (quantiles 0-10-50-90-100%)."
    lines += ["", f"LQG: AR order {lqg['ar_order']} (scan: {lqg['scan']}).{winds}{gains_line} Best classical controller, "
                  f"chosen on the scan realisation: {metrics['best_classical']}."]
    against_best = () if metrics["best_classical"] == "integrator" else \
        (("gains_over_best_classical", metrics["best_classical"]),)
    for key, against in (("gains", "integrator"), *against_best):
        lines += ["", f"Against the {against} (its residual over the predictor's: above 1, the predictor is better):",
                  "", "| predictor | variance gain | RMS gain | variance gain after fitting (fitting error of each "
                  "realisation subtracted in quadrature) | contrast gain (against the classical controller best in "
                  "contrast at each separation) | paired differences (nm) |", "|---|---|---|---|---|---|"]
        for name, gain in metrics[key].items():
            if gain is None:
                lines.append(f"| {name} | diverged | | | | |")
                continue
            against = gain.get("contrast_against", {})
            lines.append(f"| {name} | {gain.get('variance', math.nan):.2f}x | {gain.get('rms', math.nan):.2f}x | "
                         f"{gain['variance_after_fitting']:.2f}x | "
                         + ", ".join(f"{v:.2f}x at {s}" + (f" ({against[s]})" if s in against else "")
                                     for s, v in gain["contrast"].items()) + " | "
                         + ", ".join(f"{v:+.1f}" for v in gain["paired_difference_nm"]) + " |")
    return "\n".join(lines) + "\n"
