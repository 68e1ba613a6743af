"""Never worse than the integrator: where a predictor does not beat the best-gain integrator on data it is not scored
on, the integrator's command (``fallback:`` of a controller, :class:`~eofnn.control.config.FallbackConfig`).

:func:`decide_fallback`, in a scenario, before the test stream is touched:

1. the best-gain integrator: ``fallback.gains`` scanned and refined on the gain-scan stream of seed ``fallback.seed``
   (:func:`~eofnn.evaluation.contenders.scan_integrator_gains`; an experiment hands over its best-gain
   integrator's scan where it is the same scan, :mod:`eofnn.evaluation.sharing`);
2. the predictor and that integrator close the loop on the validation stream (:data:`FALLBACK_STREAM`,
   ``fallback.realisations`` realisations of ``fallback.frames``, the same turbulence and noise for both); the
   settled frames of each realisation are cut into ``fallback.blocks`` blocks;
3. ``per: mode``: each block's residual variance per mode (the true residual on the actuators projected on the
   turbulence's Karhunen-Loeve modes, measured on the same stream, or on each actuator); the predictor keeps a mode
   where its mean gain over the integrator exceeds ``fallback.sigmas`` times the standard error of that mean over
   the blocks, and the composite (:class:`~eofnn.control.fallback.ModalFallback`) is run on the same stream;
4. every candidate (the predictor, the composite) is judged as a whole on the scored residual (over the pupil with
   a Shack-Hartmann), block by block against the integrator: the best of those that beat it by more than
   ``sigmas`` standard errors is deployed, the integrator otherwise.

Nothing here reads the test stream, so the evaluation that follows scores a choice made elsewhere.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

# The stability of what a fallback deploys is the analysis floor's (:func:`eofnn.analysis.linear.controller_stability`
# with ``fallback=``); re-exported here, where it was first written.
from eofnn.analysis.linear import fallback_stability  # noqa: F401
from eofnn.control.baselines import Integrator
from eofnn.control.config import FallbackConfig
from eofnn.control.fallback import ModalFallback
from eofnn.control.modal import homogeneous_covariance
from eofnn.data.config import DataConfig
from eofnn.errors import ConfigError, DivergedError
from eofnn.evaluation.config import PredictorConfig
from eofnn.evaluation.contenders import scan_integrator_gains
from eofnn.seeding import int_seed
from eofnn.sim.loop.runner import Controller, run_loop
from eofnn.sim.scenario import Scenario

#: The stream the fallback's decisions are made on: never the test stream, nor a training or gain-scan stream.
FALLBACK_STREAM = "fallback"


@dataclass
class FallbackDecision:
    """What :func:`decide_fallback` chose: ``deployed`` (``"predictor"``, ``"composite"`` or ``"integrator"``), the
    integrator's ``gain``, the modes the predictor keeps (``kept``: ``(K, M)`` columns or a ``(K,)`` actuator mask;
    ``None`` unless the composite is deployed) and the report that goes to ``metrics.json``."""

    deployed: str
    gain: float
    kept: torch.Tensor | None
    report: dict

    def build(self, make_predictor: Callable[[], Controller]) -> Controller:
        """The controller deployed (``make_predictor()``: a fresh controller of the predictor)."""
        if self.deployed == "integrator":
            return Integrator(self.gain)
        if self.deployed == "predictor":
            return make_predictor()
        return ModalFallback(make_predictor(), self.gain, self.kept)


@dataclass
class _Run:
    """One validation run: its settled residuals on the actuators ``(R, T, K)`` (``None`` when not kept), the scored
    residual RMS ``(R, T)`` and the turbulence ``(R, T, K)`` (the integrator's run only)."""

    eps: torch.Tensor | None
    scored: torch.Tensor | None
    s: torch.Tensor | None = None
    diverged_frame: int | None = None


def _validate(controller: Controller, cfg: FallbackConfig, scenario: Scenario, divergence_factor: float,
              turbulence: bool = False) -> _Run:
    record = ("eps", "s") if turbulence else ("eps",)
    result = run_loop(scenario.turbulence(cfg.seed, FALLBACK_STREAM, cfg.realisations), scenario.plant, controller,
                      cfg.frames, noise_seed=int_seed(cfg.seed, FALLBACK_STREAM), record=record,
                      divergence_factor=divergence_factor, progress=False)
    if result.diverged:
        return _Run(None, None, diverged_frame=result.diverged_frame)
    rms = result.residual_rms_nm if result.pupil_residual_rms_nm is None else result.pupil_residual_rms_nm
    settle = cfg.settle_frames
    return _Run(result.telemetry.eps[:, settle:], rms[:, settle:],
                result.telemetry.s[:, settle:] if turbulence else None)


def _blocks(values: torch.Tensor, blocks: int) -> torch.Tensor:
    """``(R, T, ...)`` squared residuals averaged over each of ``blocks`` blocks of frames: ``(R * blocks, ...)``."""
    r, t = values.shape[:2]
    length = t // blocks
    return values[:, :length * blocks].reshape(r, blocks, length, *values.shape[2:]).mean(2).flatten(0, 1)


def _gain(integrator: torch.Tensor, candidate: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean over blocks of the integrator's residual variance minus the candidate's (nm²), and its standard error."""
    difference = integrator - candidate
    return difference.mean(0), difference.std(0) / math.sqrt(difference.shape[0])


def kl_modes(s: torch.Tensor, scenario: Scenario) -> torch.Tensor:
    """``(K, K)`` Karhunen-Loeve modes of ``(R, T, K)`` turbulence on the actuators, by decreasing variance (the
    covariance homogenised over actuator separations, as :mod:`eofnn.control.modal` does)."""
    flat = (s - s.mean((0, 1))).reshape(-1, s.shape[-1]).to(torch.float64)
    covariance = homogeneous_covariance(flat.T @ flat / flat.shape[0], torch.as_tensor(scenario.grid.indices))
    variance, modes = torch.linalg.eigh(covariance)
    return modes.flip(1)


def fallback_scan_config(cfg: FallbackConfig) -> PredictorConfig:
    """The best-gain integrator whose gain scan a fallback runs: ``cfg.gains`` on ``cfg.frames`` frames of the
    gain-scan stream of seed ``cfg.seed``, the integrator's defaults otherwise (no leak, its refinement)."""
    return PredictorConfig(controller="integrator", gains=list(cfg.gains),
                           data=DataConfig(frames=cfg.frames, seed=cfg.seed))


def decide_fallback(make_predictor: Callable[[], Controller], cfg: FallbackConfig, scenario: Scenario,
                    divergence_factor: float = 10.0, scan_settle_frames: int | None = None,
                    scan: dict | None = None) -> FallbackDecision:
    """Whether, and where, the predictor ``make_predictor()`` beats the best-gain integrator (module docstring).

    ``scan_settle_frames`` (default ``cfg.settle_frames``): the frames the gain scan leaves out, as an experiment's
    best-gain integrator does (its ``evaluation.settle_frames``): with the same ``gains``, ``frames`` and seed as
    that integrator's ``gains``, ``data.frames`` and ``data.seed``, the scan is the same, and so is the gain.
    ``scan``: that scan (:func:`~eofnn.evaluation.contenders.scan_integrator_gains` of :func:`fallback_scan_config`
    with those settle frames), already run; ``None``: run here."""
    if scan is None:
        settle = cfg.settle_frames if scan_settle_frames is None else scan_settle_frames
        scan = scan_integrator_gains(fallback_scan_config(cfg), scenario, settle, divergence_factor)
    gain = scan["gain"]
    report = {"per": cfg.per, "integrator_gain": gain, "gain_scan": scan["scanned"], "sigmas": cfg.sigmas,
              "stream": {"name": FALLBACK_STREAM, "seed": cfg.seed, "frames": cfg.frames,
                         "settle_frames": cfg.settle_frames, "realisations": cfg.realisations, "blocks": cfg.blocks}}
    integrator = _validate(Integrator(gain), cfg, scenario, divergence_factor, turbulence=cfg.per == "mode")
    if integrator.scored is None:
        raise DivergedError(f"the best-gain integrator (gain {gain:g}) diverged on the fallback's validation stream "
                            f"at frame {integrator.diverged_frame}: check fallback.gains")
    baseline = _blocks(integrator.scored.pow(2), cfg.blocks)
    medians = {"integrator": float(integrator.scored.median())}
    predictor = _validate(make_predictor(), cfg, scenario, divergence_factor)
    if predictor.scored is None:
        report.update(deployed="integrator", validation_median_rms_nm={**medians, "predictor": None},
                      why=f"the predictor diverged at frame {predictor.diverged_frame} of the validation stream")
        return FallbackDecision("integrator", gain, None, report)
    candidates = {"predictor": (predictor, None)}
    if cfg.per == "mode":
        kept = _per_mode(integrator, predictor, cfg, scenario, report)
        if kept is not None:
            composite = _validate(ModalFallback(make_predictor(), gain, kept), cfg, scenario, divergence_factor)
            if composite.scored is not None:
                candidates["composite"] = (composite, kept)
            else:
                medians["composite"] = None
    judged = {}
    for name, (run, _) in candidates.items():
        mean, se = _gain(baseline, _blocks(run.scored.pow(2), cfg.blocks))
        medians[name] = float(run.scored.median())
        judged[name] = {"gain_nm2": float(mean), "scatter_nm2": float(se), "wins": bool(mean > cfg.sigmas * se)}
    report.update(validation_median_rms_nm=medians, whole=judged)
    winners = [name for name in judged if judged[name]["wins"]]
    if not winners:
        best = max(judged, key=lambda name: judged[name]["gain_nm2"])
        report.update(deployed="integrator", why=(
            f"no candidate beats the integrator by more than {cfg.sigmas:g} standard errors on the validation "
            f"stream (best: {best}, {judged[best]['gain_nm2']:+.3g} +- {judged[best]['scatter_nm2']:.2g} nm²)"))
        return FallbackDecision("integrator", gain, None, report)
    deployed = max(winners, key=lambda name: judged[name]["gain_nm2"])
    report.update(deployed=deployed, why=(
        f"the {deployed} beats the integrator by {judged[deployed]['gain_nm2']:.3g} +- "
        f"{judged[deployed]['scatter_nm2']:.2g} nm² of residual variance on the validation stream"))
    return FallbackDecision(deployed, gain, candidates[deployed][1], report)


def decide_on_telemetry(predictor_rms_nm, own_rms_nm, blocks: int = 8, sigmas: float = 2.0) -> dict:
    """:func:`decide_fallback`'s whole decision on recorded telemetry (``eofnn replay``, the guard on a user's own
    record): the predictor's replayed error and the residual the telemetry's own controller (the integrator that
    recorded it) left, frame by frame (RMS over the actuators, nm), cut into ``blocks`` consecutive blocks; the
    predictor is deployed where its mean gain in residual variance over the blocks exceeds ``sigmas`` standard errors
    of that mean, the telemetry's own controller is kept otherwise. The own controller's residual holds the dither
    it recorded with, the replay's does not: a dithered record favours the predictor by about the dither's variance."""
    own = torch.as_tensor(own_rms_nm, dtype=torch.float64).pow(2)[None]
    predicted = torch.as_tensor(predictor_rms_nm, dtype=torch.float64).pow(2)[None]
    if own.shape[1] < 2 * blocks:
        raise ConfigError(f"guard blocks={blocks}: the replay has only {own.shape[1]} frames (at least 2 per block)")
    mean, se = _gain(_blocks(own, blocks), _blocks(predicted, blocks))
    mean, se = float(mean), float(se)
    deployed = "predictor" if mean > sigmas * se else "own_controller"
    why = (f"the predictor beats the telemetry's own controller by {mean:.3g} +- {se:.2g} nm² of residual variance"
           if deployed == "predictor" else
           f"the predictor does not beat the telemetry's own controller by more than {sigmas:g} standard errors "
           f"({mean:+.3g} +- {se:.2g} nm²): the own controller is kept")
    return {"deployed": deployed, "gain_nm2": mean, "scatter_nm2": se, "sigmas": sigmas, "blocks": blocks,
            "frames": int(own.shape[1]), "why": why}


def _per_mode(integrator: _Run, predictor: _Run, cfg: FallbackConfig, scenario: Scenario,
              report: dict) -> torch.Tensor | None:
    """The modes the predictor keeps (``(K, M)`` columns, or an actuator mask), ``None`` when it keeps none or all
    (then the composite is the integrator or the predictor); the per-mode figures go to ``report``."""
    basis = kl_modes(integrator.s, scenario) if cfg.modes == "kl" else None

    def per_mode(eps: torch.Tensor) -> torch.Tensor:
        return _blocks((eps if basis is None else eps @ basis).pow(2), cfg.blocks)

    mean, se = _gain(per_mode(integrator.eps), per_mode(predictor.eps))
    keep = mean > cfg.sigmas * se
    worse = mean < -cfg.sigmas * se
    n = int(keep.numel())
    report.update(modes=cfg.modes, n_modes=n, predictor_modes=int(keep.sum()),
                  fallen_back={"worse": worse.nonzero().flatten().tolist(),
                               "within_scatter": (~keep & ~worse).nonzero().flatten().tolist()},
                  per_mode={"gain_nm2": [float(f"{v:.4g}") for v in mean.tolist()],
                            "scatter_nm2": [float(f"{v:.3g}") for v in se.tolist()]})
    if not keep.any() or keep.all():
        return None
    return keep if basis is None else basis[:, keep]
