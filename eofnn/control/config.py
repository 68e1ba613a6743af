"""Values the controllers' configs accept, free of torch: the command line checks a config against them before the
controllers (:mod:`eofnn.control.classical`, which re-exports them) are imported; the configuration of
predictive Fourier control (:class:`PfcConfig`) and of the fallback to the best-gain integrator
(:class:`FallbackConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

from eofnn.errors import ConfigError
from eofnn.validation import COUNT, Constraint, Interval, OneOf, validated

#: Polynomial orders of the POL extrapolator: 0 is a POL zero-order hold, 1 linear, 2 quadratic.
EXTRAPOLATION_ORDERS = (0, 1, 2)
#: The most extra POL frames an extrapolator's least-squares fit may average over (``smoothing``).
MAX_EXTRAPOLATION_SMOOTHING = 16
#: The ``ar_order`` of an LQG's per-mode random-walk model (:func:`eofnn.control.kalman.fit_random_walk`: ``a1 = 1``,
#: the model whose Kalman filter is the pseudo-open-loop integrator).
RANDOM_WALK = 0
#: Orders of the per-mode autoregressive model of an LQG controller (:mod:`eofnn.control.kalman`); 0: the random walk.
AR_ORDERS = (RANDOM_WALK, 1, 2)
#: The most frozen-flow layers a predictive Fourier controller models.
MAX_PFC_LAYERS = 4
#: The noise covariances predictive Fourier control may assume (:attr:`PfcConfig.noise_covariance`).
PFC_NOISE_COVARIANCES = ("white", "reconstructor")
#: The most memories a scan of PFC's ``alpha`` tries past its grid's edge (:func:`alpha_past_edge`).
MAX_EXTRA_ALPHAS = 4


def alpha_past_edge(scanned: dict[float, float | None], extra_so_far: int = 0) -> float | None:
    """The next memory ``alpha`` a scan of predictive Fourier control tries past its grid's edge, or ``None``.

    ``scanned`` maps each alpha tried to its median residual (``None``: diverged). When the lowest residual is at
    the highest alpha tried (the residual still falling towards 1): ``1 - (1 - best) / 2``, twice the memory; at
    the lowest alpha tried (and above 0.5): ``max(0.5, 1 - 2 (1 - best))``, half of it; else, or after
    :data:`MAX_EXTRA_ALPHAS` extra alphas, ``None``. As the best-gain integrator's scan climbs past its grid
    (:func:`eofnn.interop.loop.scan_integrator`), the choice is then never the grid's edge unless it is the edge of
    what helps.
    """
    finite = {alpha: rms for alpha, rms in scanned.items() if rms is not None}
    if not finite or extra_so_far >= MAX_EXTRA_ALPHAS or len(scanned) < 2:
        return None
    best = min(finite, key=finite.get)
    if best == max(scanned):
        candidate = float(f"{1 - (1 - best) / 2:.8g}")
    elif best == min(scanned) and best > 0.5:
        candidate = max(0.5, float(f"{1 - 2 * (1 - best):.8g}"))
    else:
        return None
    return None if candidate in scanned or candidate >= 1 else candidate


#: The scalars on an LQG's identified measurement-noise variance its scan tries with each model
#: (:func:`eofnn.control.modal.lqg_from_pol`'s ``noise_scale``): the filter's bandwidth knob, as the integrator's
#: gain is the integrator's (a model fitted on POL values that carry aliasing is too confident in them).
LQG_NOISE_SCALES = (0.25, 0.5, 1.0, 2.0, 4.0)
#: The most noise scales a scan tries past its grid's edge (:func:`noise_scale_past_edge`), per model.
MAX_EXTRA_NOISE_SCALES = 5


def noise_scale_past_edge(scanned: dict[float, float | None], extra_so_far: int = 0) -> float | None:
    """The next noise scale an LQG's scan tries past its grid's edge, or ``None``.

    ``scanned`` maps each scale tried (one model) to its median residual (``None``: diverged). When the lowest
    residual is at the largest scale tried, twice it; at the smallest, half of it; else, or after
    :data:`MAX_EXTRA_NOISE_SCALES` extra scales, or once the next one would diverge (a diverged neighbour past the
    best), ``None``: the choice is never the grid's edge unless it is the edge of what helps.
    """
    finite = {scale: rms for scale, rms in scanned.items() if rms is not None}
    if not finite or extra_so_far >= MAX_EXTRA_NOISE_SCALES or len(scanned) < 2:
        return None
    best = min(finite, key=finite.get)
    candidate = 2 * best if best == max(scanned) else best / 2 if best == min(scanned) else None
    return None if candidate is None or candidate in scanned else float(f"{candidate:.8g}")


def scan_lqg_settings(evaluate, orders=AR_ORDERS, scales=LQG_NOISE_SCALES) -> dict[tuple[int, float], float | None]:
    """An LQG's model and noise scale tuned in the loop as an integrator's gain is: ``evaluate(ar_order,
    noise_scale)`` (the median residual of that LQG on the scan realisation, ``None`` if it diverged) for every
    order of ``orders`` with every scale of ``scales``, then, per order, on past the scales' edge while its best is
    there (:func:`noise_scale_past_edge`). Returns ``{(ar_order, noise_scale): median or None}`` in the order tried;
    with :data:`RANDOM_WALK` among the orders the pseudo-open-loop integrator is among the candidates."""
    scanned: dict[tuple[int, float], float | None] = {}
    for order in dict.fromkeys(orders):
        for scale in dict.fromkeys(scales):
            scanned[(order, float(scale))] = evaluate(order, float(scale))
        extra = 0
        while (scale := noise_scale_past_edge({s: v for (o, s), v in scanned.items() if o == order}, extra)) is not None:
            scanned[(order, scale)] = evaluate(order, scale)
            extra += 1
    return scanned


@dataclass
@validated
class PfcConfig:
    """Predictive Fourier control (``controller: pfc``, :mod:`eofnn.control.fourier`): a Kalman filter per spatial
    Fourier mode whose state model is frozen-flow translation by each layer's wind.

    Parameters
    ----------
    layers : int
        Frozen-flow layers identified from the telemetry (their winds and weights, :mod:`eofnn.control.wind`);
        a layer the telemetry does not support (weight below 10%) is dropped.
    winds : list of [speed_mps, direction_deg, weight], optional
        Known layers instead of identified ones (e.g. from a profiler): speed in m/s, the direction the screen moves
        towards in degrees from +x towards +y, and the layer's share of the turbulence (weights are normalised).
    alpha : float
        Modulus of each state's frozen-flow rotation per frame, ``a(n + 1) = alpha exp(-2 pi i k.v T) a(n)``: below
        1 for stability, and the memory of the filter (about ``1 / (1 - alpha)`` frames). The prediction over the
        delay is shrunk by ``alpha^d``, a bias of ``(1 - alpha^d)`` times the turbulence: keep it close to 1.
    aliases : int
        Rings of aliased frequencies ``k + m / pitch`` (``|m_x|, |m_y| <= aliases``) in each mode's state: the
        actuator grid samples a field that is not band-limited, and its aliases move at their own temporal
        frequency (0: one state per layer, the scalar filter).
    padding : float
        Size of the FFT grid over the actuator grid's (at least 1; odd sizes: no Nyquist bin): a larger grid costs
        time for little residual (``docs/findings.md``).
    max_speed_mps : float
        Fastest wind the identification searches for, m/s.
    noise_covariance : {"white", "reconstructor"}
        The measurement noise's covariance on the actuators: ``white`` (default), the same variance on every
        actuator, uncorrelated; ``reconstructor``: a Shack-Hartmann's white slope noise through its reconstructor,
        ``R W R^T`` (spatially coloured; ``W`` the slopes' relative noise variances), scaled to the white-noise
        variance per actuator the telemetry shows. A sensor without slopes has white noise: the same as ``white``.
    """

    layers: int = 2
    winds: list[list[float]] | None = None
    alpha: float = 0.9999
    aliases: int = 1
    padding: float = 2.0
    max_speed_mps: float = 50.0
    noise_covariance: str = "white"

    _constraints: ClassVar[dict[str, Constraint]] = {
        "layers": Interval(1, MAX_PFC_LAYERS, integer=True, unit="frozen-flow layers"),
        "alpha": Interval(0.5, 1, closed="left"),
        "aliases": Interval(0, 2, integer=True, unit="rings of aliased frequencies"),
        "padding": Interval(1, 4, unit="FFT grid over the actuator grid"),
        "max_speed_mps": Interval(0, 1000, closed="right", unit="m/s"),
        "noise_covariance": OneOf(PFC_NOISE_COVARIANCES),
    }
    _where: ClassVar[str] = "pfc."

    def __post_init__(self) -> None:
        if self.winds is None:
            return
        shape = "a non-empty list of [speed_mps, direction_deg, weight] (at most {MAX_PFC_LAYERS} layers)"
        if not isinstance(self.winds, (list, tuple)) or not 1 <= len(self.winds) <= MAX_PFC_LAYERS:
            raise ConfigError(f"pfc.winds={self.winds!r} is invalid: it must be {shape.format(**globals())}")
        for wind in self.winds:
            numbers = isinstance(wind, (list, tuple)) and len(wind) == 3 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in wind)
            if not numbers or not 0 <= wind[0] <= 1000 or wind[2] <= 0:
                raise ConfigError(f"pfc.winds={self.winds!r} is invalid: {wind!r} is not [speed_mps in [0, 1000], "
                                  "direction_deg, weight > 0]")


#: How a predictor falls back to the best-gain integrator: not at all, as a whole, or mode by mode.
FALLBACK_PER = ("none", "whole", "mode")
#: The modes a per-mode fallback judges: the turbulence's Karhunen-Loeve modes, or each actuator.
FALLBACK_MODES = ("kl", "actuators")


@dataclass
@validated
class FallbackConfig:
    """Never worse than the integrator: the predictor is deployed only where it beats the best-gain integrator, on a
    validation stream of its own (never the test stream), by more than the scatter; elsewhere the integrator's
    command (:mod:`eofnn.evaluation.fallback`).

    Parameters
    ----------
    per : {"none", "whole", "mode"}
        ``none``: the predictor as it is (the default); ``whole``: the predictor or the integrator, whichever wins;
        ``mode``: per mode, the predictor's command on the modes where it wins and the integrator's on the others
        (the composite is kept only if it beats the integrator as a whole, else the better of predictor and
        integrator).
    modes : {"kl", "actuators"}
        The modes judged by ``per: mode``: the Karhunen-Loeve modes of the turbulence on the actuators (measured on
        the validation stream), or each actuator.
    gains : list of float
        Integrator gains scanned for the best-gain integrator (refined around the best, as ``gains`` of
        ``controller: integrator``), on the gain-scan stream of seed ``seed``, ``frames`` frames: the same
        ``gains``, ``frames`` and ``seed`` as an experiment's best-gain integrator (``gains``, ``data.frames``,
        ``data.seed``) make the same scan, so the fallback deploys that very integrator.
    frames : int
        Frames per realisation of the validation stream (and of the gain scan).
    settle_frames : int
        Frames of each validation run left out before the residuals are compared.
    realisations : int
        Independent turbulence realisations of the validation stream.
    blocks : int
        Each realisation's settled frames are cut into this many blocks: the scatter of the predictor's gain over the
        integrator (residual variance, per mode or over the pupil) is the standard error of its mean over the
        ``realisations x blocks`` blocks, both controllers on the same turbulence and noise.
    sigmas : float
        The predictor (or the composite) is deployed where its mean gain exceeds ``sigmas`` times that scatter.
    seed : int
        Seed of the validation stream and of the gain scan.
    """

    per: str = "none"
    modes: str = "kl"
    gains: list[float] = field(default_factory=lambda: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    frames: int = 2000
    settle_frames: int = 200
    realisations: int = 2
    blocks: int = 4
    sigmas: float = 2.0
    seed: int = 0

    _constraints: ClassVar[dict[str, Constraint]] = {
        "per": OneOf(FALLBACK_PER),
        "modes": OneOf(FALLBACK_MODES),
        "frames": Interval(16, 1_000_000, integer=True, unit="frames"),
        "settle_frames": Interval(0, 1_000_000, integer=True, unit="frames"),
        "realisations": Interval(1, 64, integer=True),
        "blocks": COUNT,
        "sigmas": Interval(0, 100, unit="standard errors"),
        "seed": Interval(0, 2**63 - 1, integer=True),
    }
    _where: ClassVar[str] = "fallback."

    def __post_init__(self) -> None:
        if not isinstance(self.gains, (list, tuple)) or not self.gains or not all(
                isinstance(g, (int, float)) and not isinstance(g, bool) and 0 < g <= 10 for g in self.gains):
            raise ConfigError(f"fallback.gains={self.gains!r} is invalid: give a non-empty list of integrator gains "
                              "in (0, 10]")
        if self.realisations * self.blocks < 2:
            raise ConfigError(f"fallback.realisations={self.realisations} x blocks={self.blocks} is invalid: the "
                              "scatter needs at least 2 blocks in all")
        if (self.frames - self.settle_frames) < 8 * self.blocks:
            raise ConfigError(f"fallback.frames={self.frames} with settle_frames={self.settle_frames} leaves "
                              f"{self.frames - self.settle_frames} frames: each of the {self.blocks} blocks needs at "
                              "least 8")

    @property
    def active(self) -> bool:
        """Whether the predictor is guarded at all (``per`` is not ``none``)."""
        return self.per != "none"


__all__ = ["AR_ORDERS", "EXTRAPOLATION_ORDERS", "FALLBACK_MODES", "FALLBACK_PER", "LQG_NOISE_SCALES",
           "MAX_EXTRAPOLATION_SMOOTHING", "MAX_EXTRA_NOISE_SCALES", "MAX_PFC_LAYERS", "RANDOM_WALK", "FallbackConfig",
           "PfcConfig", "alpha_past_edge", "noise_scale_past_edge", "scan_lqg_settings"]
