"""Windows of the loop that training through it learns from: turbulence, the sensor's noise draws and the pupil's
terms, cut from the fit's own streams and put side by side (:func:`eofnn.training.rollout.rollout` closes the loop
over them)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace

import torch
from torch.utils.data import Dataset

from eofnn.data.stream import SimulatedTelemetry, sequence_plant
from eofnn.errors import require
from eofnn.resources import require_memory
from eofnn.seeding import torch_generator
from eofnn.sim.grid import ActuatorGrid
from eofnn.sim.loop.measurement import sensed_turbulence
from eofnn.sim.loop.plant import Plant
from eofnn.sim.loop.sensing import loop_measurement


@dataclass
class LoopWindow:
    """Windows of turbulence that close the loop side by side, each from a reset, in one plant (up to its gains).

    Attributes
    ----------
    s : Tensor
        ``(batch, warmup + frames, K)`` turbulence in nm; the loop is reset at its first frame.
    noise : Tensor or None
        ``(batch, warmup + frames, noise_size)`` unit normal draws of the sensor's noise (the zonal sensor's: one per
        actuator, scaled by the plant's ``wfs_noise_nm``; a Shack-Hartmann's: one per slope, scaled by its slope noise
        and reconstructed, :class:`~eofnn.sim.loop.kernel.Measurement`); ``None``: no noise.
    plant : Plant
        The plant the windows close the loop in (delay, DM, WFS; its static DM gain: a drift is not followed).
    grid : ActuatorGrid
        The actuators (the plant's misregistration).
    warmup : int
        Frames run without gradients before those of the loss.
    dm_gain_model : float
        DM gain of the pseudo-open-loop reconstruction (open-loop histories).
    dm_gains, wfs_gains : Tensor, optional
        ``(batch, 1)``: each window's own DM and WFS gains, in place of the plant's.
    sensor : LoopSensor or str, optional
        What measures the loop: a :class:`~eofnn.sim.loop.kernel.LoopSensor` (a Shack-Hartmann scenario's turbulence,
        :class:`~eofnn.sim.loop.sensing.ShackHartmannTurbulence`) or a registered sensor's name
        (:func:`~eofnn.sim.loop.kernel.register_sensor`); ``None``: the zonal sensor.
    sensed : Tensor, optional
        ``(batch, warmup + frames, K)``: what the sensor reads of the turbulence where it is not the loop's truth
        ``s``, the real-time computer's ``R_mmse S phi`` through a Shack-Hartmann's MMSE reconstructor
        (:func:`~eofnn.sim.loop.measurement.sensed_turbulence`), as ``run_loop`` measures it; ``None``: ``s`` itself.
    pupil : dict of Tensor, optional
        Where the residual is scored over the pupil (a Shack-Hartmann scenario): the phase's ``z`` ``(batch, warmup +
        frames, K)``, ``sum`` and ``sumsq`` ``(batch, warmup + frames)``
        (:meth:`~eofnn.sim.loop.sensing.ShackHartmannTurbulence.products`); the loss is then the residual over the
        pupil (``sensor.pupil_mean_square``), as ``run_loop`` scores it. ``None``: the residual at the actuators.
    """

    s: torch.Tensor
    noise: torch.Tensor | None
    plant: Plant
    grid: ActuatorGrid
    warmup: int
    dm_gain_model: float = 1.0
    dm_gains: torch.Tensor | None = None
    wfs_gains: torch.Tensor | None = None
    sensor: object | None = None
    pupil: dict[str, torch.Tensor] | None = None
    sensed: torch.Tensor | None = None

    @property
    def samples(self) -> int:
        """Residual values in the loss: windows x frames after the warm-up x actuators."""
        batch, frames, n_act = self.s.shape
        return batch * (frames - self.warmup) * n_act


class LoopBatch:
    """The windows of one optimiser step. Not a collection, so that the DataLoader and Lightning hand it over as it
    is (Lightning refuses frozen dataclasses such as :class:`~eofnn.sim.loop.plant.Plant`);
    :func:`~eofnn.training.rollout.rollout` moves each window's tensors to the network's device."""

    def __init__(self, windows: Iterable[LoopWindow]) -> None:
        self.windows = tuple(windows)

    @property
    def samples(self) -> int:
        return sum(window.samples for window in self.windows)


def window_starts(frames: int, window: int, warmup: int) -> list[int]:
    """First frames (of the warm-up) of the windows a sequence of ``frames`` is cut into: the loss frames tile
    ``[warmup, frames)`` in windows of ``window`` frames, the last one moved back to end with the sequence (so every
    frame after the first warm-up is in a loss, some of the last ones twice); one shorter window when the sequence
    holds fewer than ``warmup + window`` frames."""
    span = min(window, frames - warmup)
    starts = list(range(0, frames - warmup - span + 1, span))
    if starts[-1] + warmup + span < frames:
        starts.append(frames - warmup - span)
    return starts


#: Most bytes one rollout's graph may hold (windows beyond it run as rollouts of their own).
ROLLOUT_BYTES = 2**29


def joined(windows: list[LoopWindow], name: str) -> torch.Tensor:
    """``(rows, 1)``: the DM or WFS gain (``name``) of every row of ``windows``, their own or their plant's."""
    return torch.cat([getattr(w, f"{name}s") if getattr(w, f"{name}s") is not None
                      else w.s.new_full((w.s.shape[0], 1), getattr(w.plant, name)) for w in windows])


def merged(windows: list[LoopWindow], max_rows: int) -> list[LoopWindow]:
    """``windows`` side by side in as few rollouts as they allow: those whose plants differ at most in their DM and
    WFS gains become one, each window keeping its gains (the same residuals, fewer and larger tensor operations), in
    pieces of at most ``max_rows`` rows."""
    groups: dict[Plant, list[LoopWindow]] = {}
    for window in windows:
        groups.setdefault(replace(window.plant, dm_gain=1.0, wfs_gain=1.0), []).append(window)
    out = []
    for plant, group in groups.items():
        first = group[0]
        if len(group) == 1 and first.s.shape[0] <= max_rows:
            out.append(first)
            continue

        s, dm_gains, wfs_gains = torch.cat([w.s for w in group]), joined(group, "dm_gain"), joined(group, "wfs_gain")
        noise = None if first.noise is None else torch.cat([w.noise for w in group])
        pupil = None if first.pupil is None else {k: torch.cat([w.pupil[k] for w in group]) for k in first.pupil}
        sensed = None if first.sensed is None else torch.cat([w.sensed for w in group])
        for i in range(0, s.shape[0], max_rows):
            rows = slice(i, i + max_rows)
            out.append(LoopWindow(s[rows], None if noise is None else noise[rows], plant, first.grid, first.warmup,
                                  first.dm_gain_model, dm_gains[rows], wfs_gains[rows], first.sensor,
                                  None if pupil is None else {k: v[rows] for k, v in pupil.items()},
                                  None if sensed is None else sensed[rows]))
    return out


class LoopWindows(Dataset):
    """The sequences of a training stream cut into windows of the loop, as :class:`LoopBatch` es: all of them in one
    (``full_batch``: one quasi-Newton step per epoch) or one per sequence.

    The same turbulence sequences, plants and WFS-noise draws as ``telemetry``, the stream whose history tensors the
    closed-form fit learns from: training through the loop sees the same data. Under ``data.plant_range`` the DM and
    WFS gains are drawn again for each window (each window restarts the loop, so it may close it in a plant of its
    own: the range is covered by many more draws than there are sequences); a misregistration is drawn per sequence,
    as the closed-form data has it.

    Parameters
    ----------
    telemetry : SimulatedTelemetry
        The stream (its scenario, history, sequences, seed, plants).
    window : int
        Frames of each window's loss.
    warmup : int
        Frames before each window's loss, run without gradients.
    full_batch : bool
        All the windows in one batch.
    """

    def __init__(self, telemetry: SimulatedTelemetry, window: int, warmup: int, full_batch: bool = True) -> None:
        super().__init__()
        frames = telemetry.data.sequence_frames
        require(frames > warmup + telemetry.spec.first_frame,
                f"optimization.loop_warmup={warmup} leaves no frame to train on in the {telemetry.stream} sequences "
                f"of {frames} frames (data.sequence_frames, or the stream's frames when fewer): it must be below "
                f"{frames - telemetry.spec.first_frame}")
        self.telemetry, self.window, self.warmup, self.full_batch = telemetry, window, warmup, full_batch
        self.starts = window_starts(frames, window, warmup)
        span, n_act = min(window, frames - warmup) + warmup, telemetry.scenario.grid.n_actuators
        # A rollout's graph keeps about 3 taps + 12 tensors of (rows, K) per frame; the windows (turbulence and noise)
        # are kept, twice while they are put side by side.
        self.max_rows = max(1, ROLLOUT_BYTES // (span * n_act * (3 * telemetry.spec.n_taps + 12) * 8))
        sensor = telemetry.scenario.sensor
        noisy = telemetry.scenario.plant.wfs_noise_nm > 0 or sensor.detector is not None
        noise_values = 0 if not noisy else 2 * n_act if sensor.is_shack_hartmann else n_act  # per slope: about 2 K
        pupil_values = n_act + 2 if sensor.is_shack_hartmann else 0  # z, sum, sumsq
        pupil_values += n_act if sensor.is_shack_hartmann and sensor.reconstructor == "mmse" else 0  # R_mmse S phi
        require_memory(2 * self.n_windows * span * (n_act + noise_values + pupil_values) * 8 + ROLLOUT_BYTES,
                       f"training through the loop: {self.n_windows} {telemetry.stream} windows of {span} frames and "
                       f"{n_act} actuators")
        self._batches: list[LoopBatch] | None = None

    @property
    def n_windows(self) -> int:
        """Windows of the stream: per sequence and realisation."""
        data = self.telemetry.data
        return len(self.starts) * data.realisations * self.telemetry.n_sequences

    def __len__(self) -> int:
        return 1 if self.full_batch else self.telemetry.n_sequences

    def sequence(self, index: int) -> LoopWindow:
        """The windows of sequence ``index`` side by side, ``(windows x realisations, warmup + window, K)``."""
        t, data = self.telemetry, self.telemetry.data
        name = f"{t.stream}:{index}"
        turbulence = t.scenario.turbulence(data.seed, name, data.realisations)
        s = turbulence.frames(0, data.sequence_frames)
        shack_hartmann = hasattr(turbulence, "measurement")
        # A Shack-Hartmann's, a registered sensor's name (the scenario's sensor.kind), or None: the zonal one.
        sensor = turbulence if shack_hartmann else turbulence.sensor
        plant = t.plant(index)
        pupil = sensed = None
        if shack_hartmann:  # the residual over the pupil, as the loop is scored; the MMSE computer's view of s
            mmse = turbulence.reconstructor(plant.wfs_noise_nm)
            products = turbulence.products(0, data.sequence_frames, slopes=mmse is not None, fit=False)
            pupil = {k: products[k] for k in ("z", "sum", "sumsq")}
            sensed = sensed_turbulence(products, mmse, turbulence.isolate)
            turbulence.release()
        measurement = loop_measurement(turbulence, plant)
        # The unit draws of the closed-form fit's open-loop noise (SimulatedTelemetry.telemetry): the same data.
        noise = (torch.randn((*s.shape[:2], measurement.noise_size), generator=torch_generator(data.seed, name, 1),
                             dtype=s.dtype) if measurement.noisy else None)
        span = min(self.window, data.sequence_frames - self.warmup) + self.warmup

        def cut(x: torch.Tensor) -> torch.Tensor:
            return torch.cat([x[:, start: start + span] for start in self.starts])

        gains = {}
        for field in ("dm_gain", "wfs_gain"):
            if field in (data.plant_range or {}):
                drawn = [getattr(sequence_plant(t.scenario.plant, data, f"{name}:window:{j}"), field)
                         for j in range(len(self.starts))]
                gains[f"{field}s"] = torch.tensor(drawn, dtype=s.dtype).repeat_interleave(data.realisations)[:, None]
        return LoopWindow(cut(s), None if noise is None else cut(noise), plant, t.scenario.grid, self.warmup,
                          t.dm_gain_model, **gains, sensor=sensor,
                          pupil=None if pupil is None else {k: cut(v) for k, v in pupil.items()},
                          sensed=None if sensed is None else cut(sensed))

    def batches(self) -> list[LoopBatch]:
        """The stream's batches (simulated once, then kept): every sequence's windows in one, or one per sequence,
        put side by side (:func:`merged`)."""
        if self._batches is None:
            windows = [self.sequence(index) for index in range(self.telemetry.n_sequences)]
            groups = [windows] if self.full_batch else [[window] for window in windows]
            self._batches = [LoopBatch(merged(group, self.max_rows)) for group in groups]
        return self._batches

    def __getitem__(self, index: int) -> LoopBatch:
        if not 0 <= index < len(self):
            raise IndexError(index)
        return self.batches()[index]

    def __iter__(self) -> Iterator[LoopBatch]:
        return (self[index] for index in range(len(self)))
