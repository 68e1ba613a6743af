"""The worked example, for any simulator adapter: what an observatory does with eofnn, in another simulator's loop.

:func:`run_study` takes a :class:`~eofnn.interop.loop.SimulatorAdapter` and, with eofnn's public functions only:

1. records telemetry in the simulator's own integrator loop with white dither (:func:`run_closed_loop`);
2. identifies the plant from it (:func:`eofnn.training.identify.identify_plant`: DM gain, noise, lag);
3. fits a closed-loop EOF from that telemetry alone (:func:`eofnn.training.from_telemetry.fit_from_telemetry`,
   ridge alpha chosen on its last ``val_frames``);
4. replays it on a held-out realisation recorded the same way (:func:`eofnn.evaluation.replay.replay`);
5. scans the integrator's gain in the simulator's own loop on a realisation of its own, then runs the chosen
   integrator and the EOF (as the exported runtime filter, :class:`eofnn.runtime.PredictiveFilter`, or the torch
   controller) on ``scored_realisations`` further realisations, reporting the residual OPD (median RMS after
   ``settle_frames``, :func:`eofnn.evaluation.metrics.loop_metrics`) of each;
6. runs the split controller (:class:`~eofnn.interop.loop.SplitControl`): the integrator (its chosen gain) keeps the
   ``L`` lowest-order modes of the recorded pseudo-open loop (:func:`~eofnn.interop.loop.pol_modes`), the EOF's
   command is mixed in on the rest with a share ``mix``; ``(L, mix)`` is scanned over ``integrated_modes`` x
   ``mixes`` on the integrator's scan realisation and the choice scored on the same realisations as the others
   (``L = 0, mix = 1`` is the EOF alone).

Every contender is tuned on data it is not scored on (the integrator's gain and the split's ``(L, mix)`` on the
scan's realisation, the EOF's ridge alpha on the last ``val_frames`` of its telemetry), and all are scored on the
same realisations.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import ClassVar

from eofnn.analysis.linear import dm_gain_margin
from eofnn.data.history import HistorySpec
from eofnn.errors import ConfigError
from eofnn.evaluation.replay import replay
from eofnn.interop.loop import (
    FilterControl,
    IntegratorControl,
    SplitControl,
    TorchControl,
    pol_modes,
    require_recorded,
    run_closed_loop,
    runtime_filter,
    scan_integrator,
)
from eofnn.training.from_telemetry import TelemetryDataConfig, fit_from_telemetry
from eofnn.training.identify import identify_plant
from eofnn.training.task import OptimizationConfig
from eofnn.validation import COUNT, FRACTION, Constraint, Interval, OneOf, check_value, validated

#: Relative ridge alphas searched (1e-14 to 10, two per decade): past eofnn's default 1e-2, so that a DM-gain
#: margin can be met (a closed-loop EOF fitted on Shack-Hartmann telemetry sits near its upper gain margin).
ALPHA_PATH = tuple(10 ** (k / 2) for k in range(-28, 3))


@dataclass
@validated
class StudyConfig:
    """Frames, gains and seeds of :func:`run_study` (frames at the loop rate).

    ``record_gain`` and ``gains`` are the integrator's gains as the controller believes them (a DM that applies
    ``g`` times the command makes the loop gain ``g`` times larger). ``dm_gain_interval``: the ridge alpha is the
    least-error one whose analytic stable DM-gain interval (per actuator, relative to the identified gain) holds
    it (:func:`eofnn.analysis.linear.dm_gain_margin`): a Shack-Hartmann's optical gain differs from mode to mode
    and with the residual, which a filter fitted at the edge of stability does not survive; None: no constraint.
    ``integrated_modes``: the numbers ``L`` of lowest-order modes the split controller leaves to the integrator,
    scanned with each of ``mixes`` (the EOF's share on the other modes; ``"auto"``: 0, ``K / 64`` and ``K / 16`` for
    ``K`` actuators; ``()``: no split run). ``scored_realisations``: realisations every contender is scored on
    (seeds ``seed + 2``, then ``seed + 20``, ``seed + 21``, ...).
    """

    record_frames: int = 4000
    val_frames: int = 800
    heldout_frames: int = 2000
    loop_frames: int = 2000
    settle_frames: int = 300
    warmup_frames: int = 100
    record_gain: float = 0.25
    dither_nm: float = 10.0
    gains: tuple[float, ...] = (0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45)
    history_length: int = 4
    controller: str = "runtime"
    refit_rounds: int = 1
    dm_gain_interval: tuple[float, float] | None = None
    integrated_modes: tuple[int, ...] | str = "auto"
    mixes: tuple[float, ...] = (0.25, 0.5, 1.0)
    scored_realisations: int = 1
    seed: int = 0

    _constraints: ClassVar[dict[str, Constraint]] = {
        **dict.fromkeys(("record_frames", "heldout_frames", "loop_frames", "history_length", "scored_realisations"),
                        COUNT),
        **dict.fromkeys(("val_frames", "settle_frames", "warmup_frames"), Interval(0, None, integer=True, unit="frames")),
        "controller": OneOf(("runtime", "torch")),
    }

    @classmethod
    def from_frames(cls, frames: int, gains: tuple[float, ...]) -> StudyConfig:
        """The examples' split: ``frames`` per recording, a fifth of them for validation, half for the held-out
        replay and for each closed-loop run; ``gains`` scanned for the best-gain integrator."""
        return cls(record_frames=frames, val_frames=frames // 5, heldout_frames=frames // 2, loop_frames=frames // 2,
                   gains=gains)

    def __post_init__(self) -> None:
        for mix in self.mixes:
            check_value("mixes", mix, FRACTION)
        if self.integrated_modes != "auto" and not (
                isinstance(self.integrated_modes, (tuple, list))
                and all(isinstance(m, int) and not isinstance(m, bool) and m >= 0 for m in self.integrated_modes)):
            raise ConfigError(f"integrated_modes={self.integrated_modes!r} is invalid: it must be 'auto' or a tuple of "
                              "integers >= 0 (modes left to the integrator)")
        if self.warmup_frames > self.settle_frames:
            raise ConfigError(f"warmup_frames={self.warmup_frames} is invalid: it must be <= settle_frames="
                              f"{self.settle_frames} (the integrator's warm-up is not scored)")
        if self.settle_frames >= min(self.record_frames, self.heldout_frames, self.loop_frames):
            raise ConfigError(f"settle_frames={self.settle_frames} is invalid: it must be below every run's frames")


@dataclass
class StudyResult:
    """What :func:`run_study` measured (nm unless stated); ``summary()`` is the JSON of ``metrics.json``."""

    simulator: dict
    identified: dict
    replay: dict
    integrator: dict
    eof: dict
    split: dict | None = None
    config: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return asdict(self)


def run_study(sim, config: StudyConfig | None = None, *, dm_gain_true: float | None = None) -> StudyResult:
    """Record, identify, fit, replay and run in ``sim``'s own loop (module docstring); ``dm_gain_true`` (what the
    simulator's DM applies) is only reported beside the identified gain."""
    c = config or StudyConfig()
    candidates = split_candidates(c.integrated_modes, sim.n_actuators)
    seeds = {"record": c.seed, "heldout": c.seed + 1, "loop": c.seed + 2, "scan": c.seed + 3}
    recorder = IntegratorControl(c.record_gain, c.dither_nm, seed=c.seed + 100)
    recorded = require_recorded(run_closed_loop(sim, recorder, c.record_frames, seeds["record"]), c.record_gain, sim)
    telemetry = recorded.telemetry(start=c.settle_frames)
    plant = identify_plant(telemetry)
    plant.require_identified()
    identified = {"dm_gain": plant.dm_gain, "dm_gain_se": plant.dm_gain_se, "wfs_noise_nm": plant.wfs_noise_nm,
                  "lag_frames": plant.lag_frames, "misregistration_x": plant.misregistration_x,
                  "misregistration_y": plant.misregistration_y, "dm_gain_true": dm_gain_true,
                  "dm_gain_error": None if dm_gain_true is None else plant.dm_gain / dm_gain_true - 1}

    spec = HistorySpec("closed_loop", c.history_length, sim.delay_frames)
    select = None if c.dm_gain_interval is None or not c.val_frames else {"dm_gain_interval": list(c.dm_gain_interval)}
    optimization = OptimizationConfig(alpha="auto" if c.val_frames else 1e-6, select=select, alpha_path=ALPHA_PATH)
    margin = dm_gain_margin(sim.frame_rate_hz) if select else None
    data = TelemetryDataConfig(val_frames=c.val_frames, seed=c.seed)
    fitted = fit_from_telemetry(telemetry, spec, plant=plant, data=data, optimization=optimization, margin=margin)
    refits = []
    for round_ in range(c.refit_rounds):  # closed-loop identification: refit on data the filter recorded itself
        recorder = FilterControl(runtime_filter(fitted.network, spec, fitted.predictor.dm_gain_model), c.record_gain,
                                 c.warmup_frames, c.dither_nm, seed=c.seed + 200 + round_)
        again = run_closed_loop(sim, recorder, c.record_frames, c.seed + 10 + round_)
        if again.diverged_frame is not None:  # kept as a result: the filter that diverged is then run and reported
            refits.append(f"skipped: the EOF recording its refit data diverged at frame {again.diverged_frame}")
            break
        fitted = fit_from_telemetry(again.telemetry(start=c.settle_frames), spec, plant=plant, data=data,
                                    optimization=optimization, margin=margin)
        refits.append(f"refit on {c.record_frames} frames the EOF recorded with dither")

    heldout = run_closed_loop(sim, IntegratorControl(c.record_gain, c.dither_nm, seed=c.seed + 101),
                              c.heldout_frames, seeds["heldout"]).telemetry(start=c.settle_frames)
    replayed = replay(fitted.network, spec, heldout, plant=plant).summary()

    scan = scan_integrator(sim, c.gains, c.loop_frames, seeds["scan"], c.settle_frames)
    scored = [seeds["loop"], *(c.seed + 20 + i for i in range(c.scored_realisations - 1))]

    def score(make_control) -> list[dict]:
        return [run_closed_loop(sim, make_control(), c.loop_frames, seed).metrics(c.settle_frames).summary()
                for seed in scored]

    def medians(runs: list[dict]) -> list[float | None]:
        return [run["median_rms_nm"] for run in runs]

    integrator_rms = medians(score(lambda: IntegratorControl(scan["gain"])))
    runtime = runtime_filter(fitted.network, spec, fitted.predictor.dm_gain_model)  # reset by each run's controller
    if c.controller == "runtime":
        control = FilterControl(runtime, scan["gain"], c.warmup_frames)
    else:
        control = TorchControl(fitted.controller(), sim.delay_frames)
    eof_runs = score(lambda: control)
    eof_metrics, eof_rms = eof_runs[0], medians(eof_runs)
    split = None
    if candidates:
        modes = pol_modes(telemetry, plant.dm_gain)

        def split_control(integrated: int, mix: float) -> SplitControl:
            return SplitControl(runtime, modes[:, integrated:], scan["gain"], c.warmup_frames, mix)

        scanned = {(m, x): run_closed_loop(sim, split_control(m, x), c.loop_frames, seeds["scan"]).metrics(
            c.settle_frames).median_rms_nm for m in candidates for x in c.mixes}
        stable = {k: v for k, v in scanned.items() if v is not None}
        best = min(stable, key=stable.get) if stable else None
        split_rms = [None] * len(scored) if best is None else medians(score(lambda: split_control(*best)))
        split = {"integrated_modes": None if best is None else best[0], "mix": None if best is None else best[1],
                 "gain": scan["gain"], **_scored(split_rms), "n_modes": len(modes),
                 "scan": {f"{m}, {x:g}": v for (m, x), v in scanned.items()},
                 "scan_median_rms_nm": None if best is None else stable[best]}
    return StudyResult(sim.describe(), identified,
                       {"predictor_median_rms_nm": replayed["predictor"]["median_rms_nm"],
                        "integrator_median_rms_nm": replayed["own_controller"]["median_rms_nm"],
                        "noise_nm": replayed["noise_nm"], "n_frames": replayed["n_frames"]},
                       {"best_gain": scan["gain"], **_scored(integrator_rms),
                        "scan_median_rms_nm": scan["median_rms_nm"],
                        "scan": {str(g): v for g, v in scan["scan"].items()}},
                       {**{k: eof_metrics[k] for k in ("median_rms_nm", "mean_rms_nm", "p95_rms_nm", "diverged")},
                        **_scored(eof_rms),  # its median_rms_nm is eof_metrics' own
                        "controller": c.controller, "alpha": fitted.info.get("alpha"),
                        "stable_dm_gain_interval": fitted.info.get("alpha_choice", {}).get("dm_gain_interval"),
                        "refits": refits,
                        "history": f"closed_loop, {c.history_length} taps per signal"},
                       split=split, config={**asdict(c), "seeds": {**seeds, "scored": scored}})


def _scored(medians: list[float | None]) -> dict:
    """A contender's medians on the scored realisations: the first (``median_rms_nm``), each, and their mean
    (None where one diverged)."""
    finite = None not in medians
    return {"median_rms_nm": medians[0], "realisations_median_rms_nm": medians,
            "mean_of_realisations_nm": sum(medians) / len(medians) if finite else None}


def split_candidates(integrated_modes: tuple[int, ...] | str, n_actuators: int) -> tuple[int, ...]:
    """The ``L`` values :func:`run_study` scans (``StudyConfig.integrated_modes``; ``"auto"``: 0, ``K / 64`` and
    ``K / 16``, ``K = n_actuators``), refused with one line if one is not below ``K``."""
    if integrated_modes == "auto":
        return tuple(sorted({0, n_actuators >> 6, n_actuators >> 4}))
    for m in integrated_modes:
        if m >= n_actuators:
            raise ConfigError(f"integrated_modes holds {m}: the integrator can keep at most {n_actuators - 1} of the "
                              f"simulator's {n_actuators} modes, so that the EOF commands at least one")
    return tuple(sorted(set(integrated_modes)))
