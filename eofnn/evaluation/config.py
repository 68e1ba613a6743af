"""The configuration of an experiment's controllers and of their closed-loop evaluation (YAML <-> dataclasses)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from eofnn.control.adaptation import AdaptationConfig
from eofnn.control.baselines import Integrator
from eofnn.control.config import (
    AR_ORDERS,
    EXTRAPOLATION_ORDERS,
    MAX_EXTRAPOLATION_SMOOTHING,
    FallbackConfig,
    PfcConfig,
)
from eofnn.control.registry import FROM_TELEMETRY, NEEDS_PREDICTOR, controller_names
from eofnn.data.config import DataConfig
from eofnn.data.history import HISTORY_KINDS, MAX_HISTORY_LENGTH
from eofnn.errors import ConfigError
from eofnn.evaluation.settings import setting_grid as _grid
from eofnn.evaluation.settings import with_setting
from eofnn.models.build import import_class
from eofnn.training.config import OptimizationConfig
from eofnn.validation import Constraint, Interval, IsBool, IsString, OneOf, OrNone, check_value, from_mapping, validated

#: Largest scalar on an LQG's identified noise variance (``noise_scale``, ``noise_scales``).
MAX_NOISE_SCALE = 1e4
#: Most frames of one closed-loop evaluation (per realisation).
MAX_EVALUATION_FRAMES = 10_000_000
#: Segment length of the residual PSD when ``evaluation.psd_segment_frames`` is unset, frames (a shorter run takes the
#: largest power of two its settled frames hold: :attr:`EvaluationConfig.psd_segment_frames_used`).
DEFAULT_PSD_SEGMENT_FRAMES = 1024
#: The shortest segment of a residual PSD, frames.
MIN_PSD_SEGMENT_FRAMES = 8


@dataclass
@validated
class PredictorConfig:
    """One controller of an experiment: a baseline, a predictor to train, or a saved checkpoint.

    Parameters
    ----------
    controller : str
        One of {controllers}.
    history : str, optional
        ``open_loop`` (pseudo-open-loop values) or ``closed_loop`` (commands and residuals); unset, ``open_loop``
        for a predictor to train and the checkpoint's own for a checkpoint (set, it must match the checkpoint).
    history_length : int, optional
        Frames of history; unset, 4 for a predictor to train and the checkpoint's own for a checkpoint.
    network : dict, optional
        ``{class_path: ..., init_args: {...}}`` of any ``torch.nn.Module`` mapping ``(batch, K, taps)`` to
        ``(batch, K)``; a per-actuator ``eofnn.models.linear.LinearFilter`` by default. With ``checkpoint``, naming
        the checkpoint's class here trusts it (a checkpoint may only name eofnn's own networks otherwise).
    data : DataConfig
        How the training data is simulated.
    optimization : OptimizationConfig
        How the network is fitted (closed form or SGD, ridge alpha, optimiser).
    train_in : str, optional
        Name of the scenario whose plant records the training data (trained once, reused everywhere);
        by default the predictor is trained in each scenario it is evaluated in.
    checkpoint : str, optional
        A checkpoint from ``eofnn fit`` or ``compare`` to evaluate instead of training.
    gain : float
        Integrator gain (``controller: integrator``).
    gains : list of float, optional
        Integrator gains to choose from (``controller: integrator``): in each scenario the experiment closes the
        loop with each on a stream of its own (``data.frames`` frames, seed ``data.seed``, never the test stream)
        and keeps the one with the lowest median residual, the best-gain integrator a fair comparison needs;
        ``gain`` is then not used. The gains tried, their residuals and the choice go to ``metrics.json``.
    refine_rounds : int
        Rounds of refinement of a ``gains`` scan: each tries the gains halfway between the best and its neighbours
        (down to 0, up to the analytic critical gain), and rounds go on while the best is still the highest gain
        tried (at most 6); 0 keeps the grid as given.
    leak : float
        Integrator leak (``controller: integrator``).
    adaptation : AdaptationConfig
        Online adaptation of the fitted filter while the loop runs (``method: rls | blend``), off by default.
    dm_gain_model : float, optional
        DM gain the controller believes, for the pseudo-open-loop reconstruction; unset, the predictor's own: the
        gain identified from telemetry for a predictor trained on telemetry, 1 (the nominal DM) otherwise.
    order : int
        Degree of the polynomial that ``controller: extrapolator`` extrapolates the POL signal with over the loop
        delay: 1 (linear, ``y(n) = -(3 s_hat(n-2) - 2 s_hat(n-3))`` at a two-frame delay) or 2 (quadratic); 0 is a
        POL zero-order hold.
    smoothing : int
        ``controller: extrapolator``: POL values beyond ``order + 1`` the polynomial is fitted to by least squares
        (0, the default: through ``order + 1`` values exactly). Still exact on polynomials of degree ``order``, it
        averages the WFS noise down at the cost of lag (order 1 at a two-frame delay over 4 values: noise gain 1.64
        against 3.61).
    orders : list of int, optional
        Extrapolation orders to choose from (``controller: extrapolator``), like an integrator's ``gains``: in each
        scenario the experiment closes the loop with each order (and each of ``smoothings``) on a stream of its own
        (``data.frames`` frames, seed ``data.seed``, the gain scan's stream, never the test stream) and keeps the
        lowest median residual; ``order`` and ``smoothing`` are then not used. The settings tried, their residuals
        and the choice go to ``metrics.json`` (``classical_settings``) and ``results.md``.
    smoothings : list of int, optional
        ``smoothing`` values to choose from with ``orders`` (every combination is tried); unset, ``smoothing``.
    modes : int, optional
        ``controller: modal_integrator`` or ``lqg``: the first ``modes`` KL modes get a gain (or an AR(2) model) of
        their own, the others share the one best for them together; unset, every mode has its own. Their model
        is built in each scenario from ``data.frames`` frames of telemetry recorded with an integrator
        (``data.integrator_gain``) plus ``data.dither_nm`` of dither, seed ``data.seed`` (never the test stream).
    ar_order, noise_scale : int, float
        ``controller: lqg``: each mode's autoregressive model, order 2 (the default) or 1, or 0: the random walk (the
        filter is then the pseudo-open-loop integrator); the scalar on the identified noise variance the filter uses.
    ar_orders, noise_scales : list, optional
        ``controller: lqg``: AR orders and noise scales to choose from (every combination, the scales on past the
        grid's edge while a model's best is there: :func:`eofnn.control.config.scan_lqg_settings`): in each scenario
        an LQG is built with each from the same telemetry, closes the loop on the scan stream (``data.frames``
        frames, seed ``data.seed``, never the test stream) and the lowest median residual wins.
    pfc : PfcConfig
        ``controller: pfc`` (predictive Fourier control: a frozen-flow Kalman filter per spatial Fourier mode, built
        in each scenario from ``data.frames`` frames of dithered-integrator telemetry like the LQG): ``layers``
        identified, or known ``winds``, ``alpha``, ``aliases``, ``padding``, ``max_speed_mps``.
    pfc_alphas : list of float, optional
        ``controller: pfc``: frozen-flow memories (``pfc.alpha``, each in [0.5, 1)) to choose from, like the LQG's
        ``ar_orders``: one controller is built with each from the same telemetry, closes the loop on the scan stream
        and the lowest median residual wins (``classical_settings``). A Fourier mode of a finite pupil forgets its
        past within about a pupil crossing, so the default 0.9999 can cost much (``docs/findings.md``).
    oracle : bool
        ``true``: this predictor is the contest's oracle, a bound and not a contender. It must learn from the
        simulator's truth (``data.truth``), knowledge no telescope has; the verdict never counts it as the best
        predictor, gives its ratio over the best classical controller and every predictor's ``eta``, the share of
        its variance gain reached (``evaluation.oracle: true`` adds one).
    fallback : FallbackConfig
        Never worse than the integrator: ``per: whole`` or ``per: mode`` deploys this controller only where it beats
        the best-gain integrator on a validation stream of its own by more than the scatter, the integrator's command
        elsewhere (``modes: kl | actuators``, ``gains``, ``frames``, ``realisations``, ``blocks``, ``sigmas``,
        ``seed``); which modes fell back and why go to ``metrics.json`` (``fallback``) and ``results.md``. Off
        (``per: none``) by default.
    """

    controller: str = "predictor"
    history: str | None = None
    history_length: int | None = None
    network: dict[str, Any] | None = None
    data: DataConfig = field(default_factory=DataConfig)
    optimization: OptimizationConfig = field(default_factory=OptimizationConfig)
    train_in: str | None = None
    checkpoint: str | None = None
    gain: float = 0.5
    gains: list[float] | None = None
    refine_rounds: int = 2
    leak: float = 0.0
    adaptation: AdaptationConfig = field(default_factory=AdaptationConfig)
    dm_gain_model: float | None = None
    order: int = 1
    smoothing: int = 0
    orders: list[int] | None = None
    smoothings: list[int] | None = None
    modes: int | None = None
    ar_order: int = 2
    ar_orders: list[int] | None = None
    noise_scale: float = 1.0
    noise_scales: list[float] | None = None
    pfc: PfcConfig = field(default_factory=PfcConfig)
    pfc_alphas: list[float] | None = None
    fallback: FallbackConfig = field(default_factory=FallbackConfig)
    oracle: bool = False

    _constraints: ClassVar[dict[str, Constraint]] = {
        "controller": OneOf(controller_names()),
        "history": OrNone(OneOf(HISTORY_KINDS)),
        "history_length": OrNone(Interval(1, MAX_HISTORY_LENGTH, integer=True, unit="frames")),
        "refine_rounds": Interval(0, 6, integer=True),
        "train_in": OrNone(IsString()),
        "checkpoint": OrNone(IsString()),
        "dm_gain_model": OrNone(Interval(0, 100, closed="right")),
        "order": Interval(min(EXTRAPOLATION_ORDERS), max(EXTRAPOLATION_ORDERS), integer=True),
        "smoothing": Interval(0, MAX_EXTRAPOLATION_SMOOTHING, integer=True, unit="frames"),
        "modes": OrNone(Interval(1, 1_000_000, integer=True)),
        "ar_order": OneOf(AR_ORDERS),
        "noise_scale": Interval(0, MAX_NOISE_SCALE, closed="right"),
        "oracle": IsBool(),
    }

    def __post_init__(self) -> None:
        for name, cls in (("data", DataConfig), ("optimization", OptimizationConfig), ("adaptation", AdaptationConfig),
                          ("pfc", PfcConfig), ("fallback", FallbackConfig)):
            if isinstance(getattr(self, name), dict):
                setattr(self, name, from_mapping(cls, getattr(self, name), name))
        if self.checkpoint is None:
            self.history = self.history or "open_loop"
            self.history_length = self.history_length or 4
        if self.controller not in NEEDS_PREDICTOR and self.checkpoint is not None:
            raise ConfigError(f"controller={self.controller!r} does not run a checkpoint: checkpoint="
                              f"{self.checkpoint!r} is for controller: predictor")
        if self.controller == "integrator":
            Integrator(self.gain, self.leak)  # validates gain and leak
        modal = [name for name in FROM_TELEMETRY if name != "pfc"]  # (the Fourier controller has no KL modes)
        if self.modes is not None and self.controller not in modal:
            raise ConfigError(f"modes={self.modes!r} is for controller: {' or '.join(modal)}, not "
                              f"{self.controller!r}")
        if self.noise_scale != 1.0 and self.controller != "lqg":
            raise ConfigError(f"noise_scale={self.noise_scale!r} is for controller: lqg, not {self.controller!r}")
        if self.controller != "pfc" and self.pfc != PfcConfig():
            raise ConfigError(f"pfc={vars(self.pfc)!r} is for controller: pfc, not {self.controller!r}")
        if self.gains is not None:
            if self.controller != "integrator":
                raise ConfigError(f"gains={self.gains!r} is for controller: integrator, not {self.controller!r}")
            if not isinstance(self.gains, (list, tuple)) or not self.gains:
                raise ConfigError(f"gains={self.gains!r} is invalid: give a non-empty list of integrator gains")
            for gain in self.gains:
                Integrator(gain, self.leak)
        self._check_setting_scans()
        self._check_fallback()
        if self.oracle and not (self.trains and self.data.truth):
            raise ConfigError(f"oracle: true is for a predictor the experiment trains from the simulator's truth "
                              f"(controller: predictor, no checkpoint, data.truth: true), not controller="
                              f"{self.controller!r}" + (f" with checkpoint={self.checkpoint!r}" if self.checkpoint else "")
                              + ("" if self.data.truth else " with data.truth: false"))
        if self.trains and self.optimization.fit_method == "closed_loop" and not self.data.truth:
            raise ConfigError("optimization.fit_method: closed_loop trains through the simulated loop: it needs "
                              "data.truth: true (a fit from telemetry alone has no turbulence to close it on)")
        if self.trains and self.optimization.fit_method == "closed_loop" and self.data.target != "measured":
            raise ConfigError(f"data.target={self.data.target!r} is invalid with optimization.fit_method: closed_loop: "
                              "training through the loop scores the measured s it closes on; use fit_method: "
                              "closed_form or sgd")
        if self.network is not None:
            if not isinstance(self.network, dict) or "class_path" not in self.network:
                raise ConfigError(f"network={self.network!r} is invalid: give class_path and init_args")
            if self.checkpoint is None:  # a network to train, named by the user: import it now to check it
                cls = import_class(self.network["class_path"])  # a network: torch is imported by now
                from eofnn.training.ridge import supports_closed_form

                method = self.optimization.fit_method
                if method in ("closed_form", "closed_loop") and not supports_closed_form(cls):
                    raise ConfigError(f"optimization.fit_method={method!r} needs a linear network; {cls.__name__} "
                                      "has no features()/load_solution(): use optimization.fit_method: sgd")

    def _check_fallback(self) -> None:
        """A fallback guards a controller that is not the integrator; per mode, one that reads back the command
        applied (a predictor without online adaptation)."""
        if not self.fallback.active:
            return
        if self.controller in FALLBACK_REFUSED:
            raise ConfigError(f"fallback.per={self.fallback.per!r} is for a controller that may lose to the integrator, "
                              f"not {self.controller!r}")
        if self.fallback.per == "mode" and (self.controller != "predictor" or self.adaptation.method != "none"):
            raise ConfigError(f"fallback.per: mode needs controller: predictor without adaptation (its histories read "
                              f"the composite command back), not {self.controller!r}"
                              + ("" if self.adaptation.method == "none" else
                                 f" with adaptation.method={self.adaptation.method!r}") + ": use per: whole")

    def _check_setting_scans(self) -> None:
        """``orders`` and ``smoothings`` (extrapolator), ``ar_orders`` (LQG), ``pfc_alphas``: each for its controller only, a
        non-empty list of allowed values (one line otherwise)."""
        allowed = {"orders": ("extrapolator", OneOf(EXTRAPOLATION_ORDERS).describe(), OneOf(EXTRAPOLATION_ORDERS)),
                   "smoothings": ("extrapolator", f"an integer from 0 to {MAX_EXTRAPOLATION_SMOOTHING}",
                                  Interval(0, MAX_EXTRAPOLATION_SMOOTHING, integer=True)),
                   "ar_orders": ("lqg", OneOf(AR_ORDERS).describe(), OneOf(AR_ORDERS)),
                   "noise_scales": ("lqg", f"a number > 0 and <= {MAX_NOISE_SCALE:g}",
                                    Interval(0, MAX_NOISE_SCALE, closed="right")),
                   "pfc_alphas": ("pfc", "a number from 0.5 to below 1", Interval(0.5, 1, closed="left"))}
        for name, (controller, what, constraint) in allowed.items():
            values = getattr(self, name)
            if values is None:
                continue
            if self.controller != controller:
                raise ConfigError(f"{name}={values!r} is for controller: {controller}, not {self.controller!r}")
            if not isinstance(values, (list, tuple)) or not values:
                raise ConfigError(f"{name}={values!r} is invalid: give a non-empty list of values, each {what}")
            for value in values:
                if not constraint.accepts(value):
                    raise ConfigError(f"{name}={values!r} is invalid: {value!r} is not {what}")

    @property
    def extrapolator_grid(self) -> list[dict[str, int]] | None:
        """The extrapolator settings a scan tries, ``[{"order": ..., "smoothing": ...}, ...]`` in the order given
        (``None`` when nothing is scanned: no ``orders`` or ``smoothings``)."""
        if self.orders is None and self.smoothings is None:
            return None
        return _grid(order=[int(v) for v in self.orders or [self.order]],
                     smoothing=[int(v) for v in self.smoothings or [self.smoothing]])

    @property
    def setting_grid(self) -> list[dict[str, int]] | None:
        """The settings a classical controller's scan tries (:attr:`extrapolator_grid`, the LQG's
        ``[{"ar_order": ..., "noise_scale": ...}, ...]`` or PFC's ``[{"pfc.alpha": ...}, ...]``: a dotted key is a
        field of a section, :func:`with_setting`); ``None`` when nothing is scanned (the integrator's ``gains`` have
        a scan of their own)."""
        if self.pfc_alphas is not None:
            return [{"pfc.alpha": float(a)} for a in dict.fromkeys(self.pfc_alphas)]
        if self.ar_orders is not None or self.noise_scales is not None:
            return _grid(ar_order=[int(v) for v in self.ar_orders or [self.ar_order]],
                         noise_scale=[float(v) for v in self.noise_scales or [self.noise_scale]])
        return self.extrapolator_grid

    @property
    def trains(self) -> bool:
        """Whether this controller is a predictor trained by the experiment (not a baseline or a checkpoint)."""
        return self.controller in NEEDS_PREDICTOR and self.checkpoint is None


#: Controllers a fallback does not guard: the integrators themselves and the references that are not deployed.
FALLBACK_REFUSED = ("integrator", "dithered_integrator", "uncorrected", "pseudo_integrator")

# The help lists the registry's names, so a controller added there is never missing from ``--help``.
PredictorConfig.__doc__ = PredictorConfig.__doc__.replace("{controllers}", ", ".join(controller_names()))


@dataclass
@validated
class EvaluationConfig:
    """How controllers are evaluated in closed loop.

    Parameters
    ----------
    frames : int
        Frames per run.
    settle_frames : int
        Frames discarded at the start (the loop settling) before statistics.
    realisations : int
        Independent turbulence realisations run side by side, each a turbulence seed of its own on the test stream:
        the statistics pool their frames, and the verdict (``results.md``, ``metrics.json``) gives the spread of
        their medians (with 1, none).
    seed : int
        Seed of the test stream (a stream of its own: never shared with training).
    strehl_wavelength_m : float
        Wavelength of the Maréchal Strehl, in metres.
    divergence_factor : float
        A residual above this times the turbulence RMS counts as diverged.
    psd_segment_frames : int, optional
        Segment length of the residual PSD, frames: at most the settled frames (``frames - settle_frames``).
        Unset, 1024, or when a shorter run settles fewer frames the largest power of two they hold (said in one
        line when the run starts).
    error_budget : bool or None
        Split every contender's residual into fitting, aliasing, noise and temporal terms
        (:mod:`eofnn.evaluation.budget`: two more runs of each, noise-free and with a perfect sensor; metrics.json
        ``error_budget``, results.md). ``None`` (the default): only in scenarios with a Shack-Hartmann.
    analytic_stability : bool
        Analyse every linear controller's stability (DM-gain interval, delay margin) and report it (the default).
        ``false`` skips it: a neighbourhood filter's coupled analysis can take minutes of CPU on a busy machine
        (``docs/findings.md``), which a study of residuals alone does without.
    oracle : bool
        Add an oracle to the contest (named ``oracle``, :func:`~eofnn.evaluation.contenders.oracle_config`): the
        least-squares open-loop filter fitted on the simulator's truth with ample data, more taps and a wider
        neighbourhood than any contender; the verdict gives its ratio over the best classical controller and every
        predictor's share of its gain (``eta``). Off by default: it trains the contest's largest filter in every scenario.
    """

    frames: int = 5000
    settle_frames: int = 500
    realisations: int = 1
    seed: int = 1
    strehl_wavelength_m: float = 1.65e-6
    divergence_factor: float = 10.0
    psd_segment_frames: int | None = None
    error_budget: bool | None = None
    analytic_stability: bool = True
    oracle: bool = False

    _constraints: ClassVar[dict[str, Constraint]] = {
        "frames": Interval(2, MAX_EVALUATION_FRAMES, integer=True),
        "settle_frames": Interval(0, MAX_EVALUATION_FRAMES, integer=True),
        "realisations": Interval(1, 1024, integer=True),
        "seed": Interval(0, 2**63 - 1, integer=True),
        "strehl_wavelength_m": Interval(0, 1e-3, closed="right", unit="m"),
        "divergence_factor": Interval(1, 1e6, closed="right"),
        "psd_segment_frames": OrNone(Interval(MIN_PSD_SEGMENT_FRAMES, MAX_EVALUATION_FRAMES, integer=True)),
        "error_budget": OrNone(IsBool()),
        "analytic_stability": IsBool(),
        "oracle": IsBool(),
    }
    _where: ClassVar[str] = "evaluation."

    def __post_init__(self) -> None:
        if self.settle_frames >= self.frames:
            raise ConfigError(f"evaluation.settle_frames={self.settle_frames} is invalid: it must be below "
                              f"evaluation.frames={self.frames}")
        settled = self.frames - self.settle_frames
        if self.psd_segment_frames is not None:  # the user's choice: it fits, or it is refused
            check_value("psd_segment_frames", self.psd_segment_frames,
                        Interval(MIN_PSD_SEGMENT_FRAMES, settled, integer=True, unit="at most the settled frames"),
                        "evaluation.")
        elif settled < MIN_PSD_SEGMENT_FRAMES:
            raise ConfigError(f"evaluation.frames={self.frames} with settle_frames={self.settle_frames} leaves "
                              f"{settled} settled frame(s): a residual PSD needs at least {MIN_PSD_SEGMENT_FRAMES}")

    @property
    def psd_segment_frames_used(self) -> int:
        """The residual PSD's segment length, frames: ``psd_segment_frames`` when set; unset,
        :data:`DEFAULT_PSD_SEGMENT_FRAMES`, or the largest power of two within the settled frames when fewer."""
        if self.psd_segment_frames is not None:
            return self.psd_segment_frames
        settled = self.frames - self.settle_frames
        return min(DEFAULT_PSD_SEGMENT_FRAMES, 1 << (settled.bit_length() - 1))

    @property
    def psd_segment_note(self) -> str | None:
        """One line when the unset segment length is shortened to fit a short run (``None`` otherwise)."""
        if self.psd_segment_frames is not None or self.psd_segment_frames_used == DEFAULT_PSD_SEGMENT_FRAMES:
            return None
        return (f"evaluation.psd_segment_frames: {self.psd_segment_frames_used} (the default {DEFAULT_PSD_SEGMENT_FRAMES} is "
                f"longer than the {self.frames - self.settle_frames} settled frames)")


__all__ = ["DEFAULT_PSD_SEGMENT_FRAMES", "EvaluationConfig", "PredictorConfig", "with_setting"]
