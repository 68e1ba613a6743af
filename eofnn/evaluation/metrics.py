"""Closed-loop evaluation metrics: spatial RMS per frame, its statistics, Maréchal Strehl, residual PSD."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from eofnn.sim.loop.runner import LoopResult


class WelchPSD:
    """Temporal power spectrum of the residual, accumulated chunk by chunk (Hann-windowed, non-overlapping).

    The PSD is one-sided, in nm²/Hz, averaged over actuators, realisations and segments; frames before
    ``settle_frames`` are skipped. Feed it through :func:`eofnn.sim.run_loop`'s ``on_chunk``.

    Which residual (:attr:`residual`): the zonal loop's ``eps = s + DM(y)`` at the actuators (``"eps"``). Where the
    chunks carry ``fit`` (a Shack-Hartmann or pyramid loop, scored over the pupil) it is ``fit + DM(y) = eps - s +
    fit`` (``"dm_fit"``): the command-space residual against the DM's fit of the true phase ``P F phi``, the part of
    the pupil's residual a controller can act on (no fitting error, no aliasing). Not ``eps``: there ``s = R S phi``
    is the sensor's reconstruction, aliasing included, whose slow large-scale difference from ``P F phi`` at the
    pupil's edge an anti-aliasing predictor (``data.target: dm_fit``) rightly leaves alone, and ``eps`` would show it
    as that predictor's own low-frequency residual (``docs/findings.md``). Piston is in both, as in every contender.
    """

    def __init__(self, segment_frames: int, frame_rate_hz: float, settle_frames: int = 0) -> None:
        self.segment, self.rate, self.settle = segment_frames, frame_rate_hz, settle_frames
        self._buffer: list[torch.Tensor] = []
        self._buffered = 0
        self._sum: torch.Tensor | None = None
        self._count = 0
        window = torch.hann_window(segment_frames, periodic=False, dtype=torch.float64)
        self._window = window.view(1, -1, 1)
        self._norm = float(frame_rate_hz * window.pow(2).sum())
        self.residual = "eps"

    def __call__(self, first_frame: int, arrays: dict[str, torch.Tensor]) -> None:
        eps = arrays["eps"]
        if "fit" in arrays:  # against the DM's fit of the true phase (class docstring)
            eps, self.residual = eps - arrays["s"] + arrays["fit"], "dm_fit"
        skip = max(0, self.settle - first_frame)
        if skip >= eps.shape[1]:
            return
        self._buffer.append(eps[:, skip:])
        self._buffered += eps.shape[1] - skip
        while self._buffered >= self.segment:
            data = torch.cat(self._buffer, 1)
            segment, rest = data[:, : self.segment], data[:, self.segment:]
            spectrum = torch.fft.rfft(segment * self._window, dim=1).abs().pow(2) / self._norm
            spectrum[:, 1:-1] *= 2  # one-sided
            power = spectrum.mean(dim=(0, 2))
            self._sum = power if self._sum is None else self._sum + power
            self._count += 1
            self._buffer, self._buffered = [rest], rest.shape[1]

    def result(self) -> tuple[list[float], list[float]]:
        """Frequencies (Hz) and PSD (nm²/Hz); empty when fewer than ``segment_frames`` settled frames ran."""
        if self._sum is None:
            return [], []
        freqs = torch.fft.rfftfreq(self.segment, d=1 / self.rate)
        return freqs.tolist(), (self._sum / self._count).tolist()


class GrowthMonitor:
    """Sees a loop that diverges slowly: a residual that keeps growing without (yet) exceeding any fixed multiple of
    the turbulence, as a loop just past its stability margin does for thousands of frames.

    The mean squares of each actuator's residual and turbulence are accumulated over blocks of ``block_frames``
    after ``settle_frames``; over the last half of the run (at least ``MIN_BLOCKS`` blocks), a straight line fitted
    to the log of each actuator's block power gives its exponential growth rate, less the turbulence's own growth
    at that actuator (the turbulence waxes and wanes over seconds: a residual that follows it is not diverging).
    The loop is *diverging* when, for some
    actuator, that growth is significant (t-statistic above :attr:`T_STAT`, a strict threshold since 1000s of
    actuators are tested and blocks are correlated), at least doubles the amplitude over the window, and is
    sustained: the mean log power rises in each of :attr:`SEGMENTS` consecutive segments (a step change, a new wind,
    rises in one). Feed it through :func:`eofnn.sim.run_loop`'s ``on_chunk``.
    """

    MIN_BLOCKS = 12
    T_STAT = 8.0
    SEGMENTS = 4

    def __init__(self, frame_rate_hz: float, settle_frames: int = 0, block_frames: int = 50) -> None:
        self.rate, self.settle, self.block = frame_rate_hz, settle_frames, block_frames
        self._blocks: list[torch.Tensor] = []
        self._partial: torch.Tensor | None = None
        self._filled = 0

    def __call__(self, first_frame: int, arrays: dict[str, torch.Tensor]) -> None:
        skip = max(0, self.settle - first_frame)
        # The turbulence's power is kept beside the residual's: it waxes and wanes over seconds at an actuator (large
        # scales crossing the pupil), and a residual that only follows it is not a loop diverging.
        power = torch.stack([arrays["eps"][:, skip:].pow(2).mean(0), arrays["s"][:, skip:].pow(2).mean(0)])
        while power.shape[1]:
            take = min(self.block - self._filled, power.shape[1])
            part = power[:, :take].sum(1)
            self._partial = part if self._partial is None else self._partial + part
            self._filled += take
            power = power[:, take:]
            if self._filled == self.block:
                self._blocks.append(self._partial / self.block)  # (2, K): residual and turbulence power
                self._partial, self._filled = None, 0

    def result(self) -> dict | None:
        """``{"diverging", "growth_rate_per_s", "t_stat", "actuator", "window_s"}`` (amplitude growth rate of the
        fastest-growing actuator, 1/s); ``None`` when the run is too short to judge."""
        n = len(self._blocks) // 2
        if n < self.MIN_BLOCKS:
            return None
        logs = torch.stack(self._blocks[-n:]).clamp(min=1e-300).log()  # (n, 2, K)
        t = (torch.arange(n, dtype=torch.float64) * self.block / self.rate).view(-1, 1, 1)
        tc = t - t.mean()
        slopes = (tc * (logs - logs.mean(0))).sum(0) / tc.pow(2).sum()  # (2, K)
        residual = logs[:, 0] - logs[:, 0].mean(0) - slopes[0] * tc[:, 0]
        stderr = (residual.pow(2).sum(0) / (n - 2)).sqrt() / tc.pow(2).sum().sqrt()
        t_stat = slopes[0] / stderr.clamp(min=1e-300)
        # Growth beyond the turbulence's own at the same actuator, significant in the residual itself.
        excess = slopes[0] - slopes[1].clamp(min=0)
        worst = int(torch.where(t_stat > self.T_STAT, excess, torch.full_like(excess, -math.inf)).argmax())
        if not torch.isfinite(excess[worst]) or t_stat[worst] <= self.T_STAT:
            worst = int(excess.argmax())
        window = float(n * self.block / self.rate)
        rate = float(excess[worst]) / 2  # of the amplitude: half that of the power
        relative = logs[:, 0, worst] - logs[:, 1, worst]
        means = torch.stack([seg.mean() for seg in relative.tensor_split(self.SEGMENTS)])
        sustained = bool((means.diff() > 0.25 * float(excess[worst]) * window / self.SEGMENTS).all())
        diverging = bool(t_stat[worst] > self.T_STAT and rate * window >= math.log(2) and sustained)
        return {"diverging": diverging, "growth_rate_per_s": rate, "t_stat": float(t_stat[worst]),
                "actuator": worst, "window_s": window}


@dataclass
class LoopMetrics:
    """Metrics of one closed-loop run (nm unless stated); statistics are ``None`` when the loop diverged."""

    median_rms_nm: float | None
    mean_rms_nm: float | None
    p95_rms_nm: float | None
    strehl: float | None
    diverged: bool
    diverged_frame: int | None
    settle_frames: int
    n_frames: int
    rms_nm: list[float] = field(default_factory=list, repr=False)
    psd_freq_hz: list[float] = field(default_factory=list, repr=False)
    psd_nm2_per_hz: list[float] = field(default_factory=list, repr=False)
    #: The residual the PSD is of (:attr:`WelchPSD.residual`): ``"eps"`` (``s + DM(y)`` at the actuators) or
    #: ``"dm_fit"`` (``P F phi + DM(y)``, against the DM's fit of the true phase: a scenario scored over the pupil).
    psd_residual: str = "eps"
    #: First frame at which an adaptive controller fell back to its integrator (``None``: it never did, or n/a).
    fallback_frame: int | None = None
    #: Raw contrast behind a perfect coronagraph (at ``strehl_wavelength_m``): separations in lambda/D, the profile,
    #: and the values at 2, 3, 5 and 10 lambda/D (empty when the loop diverged).
    contrast_separation_lod: list[float] = field(default_factory=list, repr=False)
    contrast: list[float] = field(default_factory=list, repr=False)
    contrast_at: dict[str, float | None] = field(default_factory=dict)
    #: The residual's RMS (nm) inside the control radius's circle, in the control square's corners and beyond the
    #: square, on the frames the contrast propagates (:meth:`RawContrast.spatial_split`); None when diverged.
    spatial_split_nm: dict[str, float] | None = None
    #: Non-stationary scenarios: per change, the re-convergence after it (:mod:`eofnn.evaluation.nonstationary`).
    reconvergence: list[dict] | None = None
    #: Slow divergence (:class:`GrowthMonitor`): whether the residual keeps growing, and how fast (amplitude, 1/s).
    diverging: bool = False
    growth: dict | None = None
    #: The median RMS of each turbulence realisation on its own (``evaluation.realisations`` of them, each a different
    #: turbulence seed of the test stream): the spread the verdict reports. Empty when the loop diverged. Not in
    #: :meth:`summary` (the pooled median above is the headline number).
    realisation_median_rms_nm: list[float] = field(default_factory=list, repr=False)
    #: The raw contrast at the reported separations (as ``contrast_at``) of each turbulence realisation on its own, in
    #: the order of ``realisation_median_rms_nm``: the verdict's spread. Empty when the loop diverged. Not in
    #: :meth:`summary`.
    realisation_contrast_at: list[dict[str, float | None]] = field(default_factory=list, repr=False)
    #: Where the residual is scored: ``"actuators"`` (the zonal sensor) or ``"pupil"`` (a Shack-Hartmann scenario:
    #: the statistics above are then the piston-removed RMS over the pupil on the fine grid, fitting error included).
    residual_over: str = "actuators"
    #: A Shack-Hartmann scenario's median RMS of the command-space residual ``s + DM(y)`` at the actuators.
    actuator_median_rms_nm: float | None = None
    #: The error budget (:mod:`eofnn.evaluation.budget`), when one was asked for or the scenario has a real sensor.
    error_budget: dict | None = None
    #: A pyramid scenario's optical gains on an integrator's closed-loop residual, per Karhunen-Loeve mode and their
    #: low- and high-order means (:class:`eofnn.sim.sensing.optical_gains.OpticalGainProbe`).
    optical_gains: dict | None = None

    def summary(self) -> dict:
        """The JSON-ready scalars (``fallback_frame`` only when an adaptive controller fell back, ``reconvergence``
        only in a scenario with changes)."""
        out = {k: getattr(self, k) for k in ("median_rms_nm", "mean_rms_nm", "p95_rms_nm", "strehl", "diverged",
                                             "diverged_frame", "settle_frames", "n_frames")}
        if self.fallback_frame is not None:
            out["fallback_frame"] = self.fallback_frame
        if self.reconvergence is not None:
            out["reconvergence"] = self.reconvergence
        out["diverging"] = self.diverging
        if self.growth is not None:
            out["growth"] = self.growth
        if self.residual_over != "actuators":
            out["residual_over"] = self.residual_over
            out["actuator_median_rms_nm"] = self.actuator_median_rms_nm
        if self.error_budget is not None:
            out["error_budget"] = self.error_budget
        if self.spatial_split_nm is not None:
            out["spatial_split_nm"] = self.spatial_split_nm
        if self.optical_gains is not None:
            out["optical_gains"] = self.optical_gains
        return out


def marechal_strehl(rms_nm: torch.Tensor, wavelength_m: float) -> torch.Tensor:
    """Strehl ratio by the Maréchal approximation, ``exp(-(2 pi sigma / lambda)^2)``."""
    return torch.exp(-(2 * math.pi * rms_nm * 1e-9 / wavelength_m) ** 2)


def loop_metrics(result: LoopResult, settle_frames: int, strehl_wavelength_m: float,
                 psd: WelchPSD | None = None) -> LoopMetrics:
    """Summarise a loop run after ``settle_frames`` (per-frame RMS pooled over realisations): the residual over the
    pupil where the run has one (a Shack-Hartmann scenario), the actuators' otherwise."""
    pupil = getattr(result, "pupil_residual_rms_nm", None)
    series = result.residual_rms_nm if pupil is None else pupil
    extra = {} if pupil is None else {"residual_over": "pupil"}
    rms = series[:, settle_frames:]
    n_frames = series.shape[1]
    freqs, power = psd.result() if psd is not None else ([], [])
    if psd is not None:
        extra["psd_residual"] = psd.residual
    if result.diverged or rms.numel() == 0:
        return LoopMetrics(None, None, None, None, result.diverged, result.diverged_frame, settle_frames, n_frames,
                           series.mean(0).tolist(), freqs, power, **extra)
    if pupil is not None:
        extra["actuator_median_rms_nm"] = float(torch.quantile(result.residual_rms_nm[:, settle_frames:].flatten(), 0.5))
    flat = rms.flatten()
    return LoopMetrics(
        median_rms_nm=float(torch.quantile(flat, 0.5)),
        mean_rms_nm=float(flat.mean()),
        p95_rms_nm=float(torch.quantile(flat, 0.95)),
        strehl=float(marechal_strehl(flat, strehl_wavelength_m).mean()),
        diverged=False,
        diverged_frame=None,
        settle_frames=settle_frames,
        n_frames=n_frames,
        rms_nm=series.mean(0).tolist(),
        psd_freq_hz=freqs,
        psd_nm2_per_hz=power,
        realisation_median_rms_nm=torch.quantile(rms, 0.5, dim=1).tolist(),
        **extra,
    )
