"""How a predictor's training data is simulated (:class:`DataConfig`), free of torch and Lightning.

The command line builds its parsers from this config and checks its values before the streams that simulate the data
(:mod:`eofnn.data.stream`, which re-exports these names) are imported: seconds of imports that ``--help`` and a
config error do without.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from eofnn.errors import require
from eofnn.validation import Constraint, Interval, IsBool, OneOf, check_value, validated

#: Most frames one fit may simulate (training plus validation): about three hours of CPU at 1264 actuators.
MAX_FRAMES = 10_000_000

#: What a simulator-truth predictor learns to cancel (``data.target``).
TARGETS = ("measured", "dm_fit")

#: Plant fields ``data.plant_range`` may draw per training sequence.
RANGED_PLANT_FIELDS = ("dm_gain", "wfs_gain", "misregistration_x", "misregistration_y")


@dataclass
@validated
class DataConfig:
    """How a predictor's training data is simulated and cut into batches.

    Parameters
    ----------
    frames : int
        Training frames per epoch (rounded up to whole sequences).
    val_frames : int
        Frames of the held-out validation stream.
    sequence_frames : int
        Frames per independent turbulence realisation.
    batch_frames : int
        Frames per batch (times ``realisations`` samples).
    realisations : int
        Realisations simulated side by side per sequence.
    seed : int
        Seed of the training and validation streams; evaluation uses its own stream.
    num_workers : int
        DataLoader worker processes.
    integrator_gain : float
        Gain of the integrator that records closed-loop data.
    dither_nm : float
        RMS white dither added to the commands while recording closed-loop data (persistent excitation).
    refit_rounds : int
        Rounds in which the just-fitted predictor (plus the same dither) records the data of the next fit.
    truth : bool
        ``true``: targets from the simulator's turbulence ``s`` (a study's labelled shortcut). ``false``: learn as
        an observatory would, from telemetry alone: record ``frames + val_frames`` frames with the dithered
        integrator, identify the plant from the dither, fit from ``y`` and ``wfs`` (the learner never sees ``s``).
    plant_range : dict, optional
        ``{field: [low, high]}`` (fields dm_gain, wfs_gain, misregistration_x, misregistration_y; e.g.
        ``{dm_gain: [0.8, 1.25]}``): each training and validation sequence is simulated in the scenario's plant
        with these fields drawn uniformly from their intervals (seeded by ``seed``, the stream and the sequence
        index). Closed-loop data is recorded in the drawn plant; open-loop data too (by the recording integrator
        plus dither), its POL values reconstructed with the DM gain the filter believes (1), so they carry the
        mismatch; targets cancel the turbulence in the drawn plant. Needs ``truth``.
    target : {"measured", "dm_fit"}
        The turbulence a simulator-truth predictor's target cancels (``-s / g``, :func:`eofnn.data.history.targets`).
        ``measured``: the loop's ``s``, as the sensor sees it (with a Shack-Hartmann its noise-free reconstruction
        ``R S phi``, aliasing included). ``dm_fit`` (a Shack-Hartmann scenario only): the DM's least-squares fit of
        the true phase over the pupil, ``P F phi``, with no aliasing (anti-aliasing prediction). Either
        way the inputs are the measured histories, and the delay and fractional delay are handled alike. Needs
        ``truth`` and a closed-form or SGD fit (training through the loop closes it on the measured ``s``).
    """

    frames: int = 20000
    val_frames: int = 2000
    sequence_frames: int = 10000
    batch_frames: int = 256
    realisations: int = 1
    seed: int = 0
    num_workers: int = 0
    integrator_gain: float = 0.5
    dither_nm: float = 10.0
    refit_rounds: int = 0
    truth: bool = True
    plant_range: dict | None = None
    target: str = "measured"

    _constraints: ClassVar[dict[str, Constraint]] = {
        "frames": Interval(1, MAX_FRAMES, integer=True),
        "val_frames": Interval(1, MAX_FRAMES, integer=True),
        "sequence_frames": Interval(2, 1_000_000, integer=True),
        "batch_frames": Interval(1, 1_000_000, integer=True),
        "realisations": Interval(1, 1024, integer=True),
        "seed": Interval(0, 2**63 - 1, integer=True),
        "num_workers": Interval(0, 64, integer=True),
        "integrator_gain": Interval(0, 10),
        "dither_nm": Interval(0, 1e5, unit="nm"),
        "refit_rounds": Interval(0, 100, integer=True),
        "truth": IsBool(),
        "target": OneOf(TARGETS),
    }
    _where: ClassVar[str] = "data."

    def __post_init__(self) -> None:
        require(self.frames * (self.refit_rounds + 1) * self.realisations <= MAX_FRAMES,
                f"data.frames={self.frames} x realisations={self.realisations} x (refit_rounds + 1) is more than "
                f"{MAX_FRAMES} frames to simulate")
        self.plant_range = check_plant_range(self.plant_range)
        require(self.plant_range is None or self.truth,
                "data.plant_range needs data.truth: true (a fit from telemetry alone learns the one plant it recorded)")
        require(self.target == "measured" or self.truth,
                f"data.target={self.target!r} needs data.truth: true (telemetry alone holds the measurement, never "
                "the DM's fit of the true phase)")

    @property
    def learns_from(self) -> str:
        """What the targets come from, in words (the experiment's log)."""
        if not self.truth:
            return "telemetry alone"
        return "simulator truth" + (", target: the DM's fit of the true phase" if self.target == "dm_fit" else "")


def check_plant_range(value: object) -> dict[str, list[float]] | None:
    """``data.plant_range`` checked and normalised to ``{field: [low, high]}`` floats (``None`` when empty); a
    one-line error for anything else: not a mapping, an unknown field, not ``[low, high]``, low above high, or an end
    outside what the plant allows for that field."""
    if value is None:
        return None
    example = "a mapping of plant fields to [low, high], e.g. {dm_gain: [0.8, 1.25]}"
    require(isinstance(value, dict), f"data.plant_range={value!r} is invalid: it must be {example}")
    from eofnn.sim.loop.plant import Plant  # the plant's own bounds (numpy only, no torch)

    ranges = {}
    for name, interval in value.items():
        require(name in RANGED_PLANT_FIELDS, f"data.plant_range has unknown field {name!r}: allowed are "
                                             f"{', '.join(RANGED_PLANT_FIELDS)}")
        require(isinstance(interval, (list, tuple)) and len(interval) == 2,
                f"data.plant_range.{name}={interval!r} is invalid: it must be [low, high]")
        for end in interval:
            check_value(f"plant_range.{name}", end, Plant._constraints[name], "data.")
        low, high = (float(end) for end in interval)
        require(low <= high, f"data.plant_range.{name}={list(interval)!r} is invalid: low must be <= high")
        ranges[name] = [low, high]
    return ranges or None


__all__ = ["MAX_FRAMES", "RANGED_PLANT_FIELDS", "TARGETS", "DataConfig", "check_plant_range"]
