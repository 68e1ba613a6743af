"""The classical controllers of a study in another simulator's loop, each built from the loop's recorded telemetry
and tuned in that loop on a realisation of its own (as eofnn's own contest tunes them): the modal integrator with
optimised gains, the LQG, and predictive Fourier control. :mod:`eofnn.studies.antialias` scores them beside the
best-gain integrator and its predictors.

``c`` in each scan is any config with ``loop_frames`` and ``settle_frames`` (frames of a tuning run, and the first of
them not scored), as :class:`eofnn.studies.antialias.AntiAliasConfig` has.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from eofnn.control.classical import ModalIntegrator
from eofnn.control.config import AR_ORDERS, LQG_NOISE_SCALES, scan_lqg_settings
from eofnn.control.modal import GAIN_MARGIN_CANDIDATES, lqg_from_pol, modal_statistics, optimal_gains
from eofnn.interop.loop import TorchControl, run_closed_loop
from eofnn.sim.layout import ActuatorLayout, layout_from_positions

#: The classical controllers a study scores beside its best-gain integrator (``"integrator"``), by name.
CLASSICAL = ("integrator", "modal", "lqg", "pfc")


def _grid_indices(sim) -> torch.Tensor | None:
    """``(K, 2)`` lattice rows and columns of ``sim``'s actuators (``None`` off a lattice): the KL modes' homogenised
    covariance (:func:`eofnn.control.modal.modal_statistics`)."""
    layout = layout_from_positions(sim.positions_m)
    indices = layout.lattice_indices if isinstance(layout, ActuatorLayout) else layout.indices
    return None if indices is None else torch.as_tensor(indices)


def scan_modal(sim, pol: torch.Tensor, dm_gain: float, c, seed: int) -> dict:
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


def scan_lqg(sim, pol: torch.Tensor, dm_gain: float, c, seed: int, orders=AR_ORDERS,
             scales=LQG_NOISE_SCALES, coloured: bool = True) -> dict:
    """The LQG (:func:`eofnn.control.modal.lqg_from_pol`: a model per KL mode, stationary Kalman filter) built from
    the recorded telemetry's ``(R, T, K)`` POL values (formed with the identified DM gain), its model (AR order 1 or
    2, or 0: the random walk, whose filter is the pseudo-open-loop integrator) and the scalar on its identified noise
    variance chosen in the loop on the scan realisation ``seed`` (:func:`~eofnn.control.config.scan_lqg_settings`,
    as eofnn's own contest tunes it); then, where the loop exposes its reconstructor and ``coloured``, the chosen
    setting once more with each mode's noise variance taken from the reconstructor's noise covariance ``R R^T``
    projected on the KL modes (scaled to the identified noise's mean over the modes; the AR fit subtracts it too),
    kept if better: ``{"controller", "ar_order", "noise_scale", "noise_covariance", "median_rms_nm", "scan"}``, the
    scan keyed ``"ar_order=.., noise_scale=.."``."""
    stats = modal_statistics(pol, grid_indices=_grid_indices(sim))
    built = {}

    def evaluate(order: int, scale: float, noise: str = "identified"):
        model_stats = stats if noise == "identified" else coloured_stats
        built[(order, scale, noise)] = lqg_from_pol(pol, sim.delay_frames, dm_gain, order, stats=model_stats,
                                                    noise_scale=scale)
        control = TorchControl(built[(order, scale, noise)], sim.delay_frames)
        return run_closed_loop(sim, control, c.loop_frames, seed).metrics(c.settle_frames).median_rms_nm

    scan = {(*key, "identified"): v for key, v in scan_lqg_settings(evaluate, orders, scales).items()}
    stable = {key: v for key, v in scan.items() if v is not None}
    best = min(stable, key=stable.get) if stable else (2, 1.0, "identified")
    reconstructor = getattr(sim, "reconstructor", None)
    if coloured and reconstructor is not None and stable:
        r = torch.as_tensor(np.asarray(reconstructor, dtype=np.float64))
        shape = ((r.T @ stats.modes).pow(2).sum(0))  # m_k^T R R^T m_k
        coloured_stats = replace(stats, noise_variance=shape * stats.noise_variance.mean() / shape.mean())
        key = (best[0], best[1], "reconstructor")
        scan[key] = evaluate(*key)
        if scan[key] is not None and scan[key] < stable[best]:
            best, stable[key] = key, scan[key]
    if best not in built:
        built[best] = lqg_from_pol(pol, sim.delay_frames, dm_gain, best[0], stats=stats, noise_scale=best[1])
    return {"controller": built[best], "ar_order": best[0], "noise_scale": best[1], "noise_covariance": best[2],
            "median_rms_nm": stable.get(best),
            "scan": {f"ar_order={o}, noise_scale={s:g}" + ("" if n == "identified" else f", noise={n}"): v
                     for (o, s, n), v in scan.items()}}


#: The frozen-flow memories (:attr:`eofnn.control.config.PfcConfig.alpha`) predictive Fourier control's scan tries:
#: new turbulence enters a finite pupil, so a Fourier mode forgets its past within about a pupil crossing (``D / v``:
#: 100 frames for 2 m at 20 m/s and 1 kHz, 400 for 8 m), and the default 0.9999 trusts it far longer (the scan that
#: chose this grid: ``docs/findings.md``).
PFC_ALPHAS = (0.98, 0.99, 0.995, 0.998)


def scan_pfc(sim, pol: torch.Tensor, plant, c, seed: int) -> dict:
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


def _best_in_loop(sim, controls: dict, c, seed: int, fallback):
    """Each of ``controls`` (by setting) closed in ``sim``'s loop on the realisation ``seed``: ``(the setting with the
    lowest median RMS, that RMS, {str(setting): RMS or None if it diverged})``; ``fallback`` and ``None`` when every
    one diverged."""
    scan = {setting: run_closed_loop(sim, control, c.loop_frames, seed).metrics(c.settle_frames).median_rms_nm
            for setting, control in controls.items()}
    stable = {setting: v for setting, v in scan.items() if v is not None}
    best = min(stable, key=stable.get) if stable else fallback
    return best, stable.get(best), {str(setting): v for setting, v in scan.items()}


__all__ = ["CLASSICAL", "PFC_ALPHAS", "scan_lqg", "scan_modal", "scan_pfc"]
