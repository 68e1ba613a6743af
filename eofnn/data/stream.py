"""Telemetry simulated on the fly, cut into history tensors: the training data of every predictor.

Anti-aliasing targets (``data.target: dm_fit``)
----------------------------------------------
With a Shack-Hartmann the loop's ``s`` is the sensor's noise-free reconstruction ``R S phi``: a predictor trained on
it learns to predict the aliasing too, and sends it back into the loop. In simulation the DM's least-squares fit of
the true phase, ``P F phi`` (:mod:`eofnn.sim.sensing.pupil`), is known: with ``dm_fit`` the targets cancel it (same
sign, DM gain and fractional-delay average as ``-s / g``), while the histories stay the measured, noisy POL values.
A filter wide enough in space and time can then learn to see through the aliasing (Correia & Teixeira 2014 do it
with a Wiener reconstructor).

The filter is fitted in command space, so it also spends itself on command modes the DM barely renders (what that
costs on ``configs/antialias_sh_small.yaml``: ``docs/findings.md``); a loss weighted by the pupil's Gram matrix is the
next step.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from dataclasses import replace

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from eofnn.data.config import MAX_FRAMES, DataConfig  # noqa: F401  (re-exported: the config's home before it moved)
from eofnn.data.history import HistorySpec, build_history, pseudo_open_loop, targets
from eofnn.errors import require
from eofnn.resources import require_memory
from eofnn.seeding import int_seed, stream_seed, torch_generator
from eofnn.sim.loop.plant import Plant
from eofnn.sim.loop.runner import Controller, record_loop
from eofnn.sim.scenario import Scenario
from eofnn.validation import COUNT, POSITIVE, check_value


def require_training_memory(scenario: Scenario, spec: HistorySpec, data: DataConfig) -> None:
    """Refuse, up front, training data that would not fit in memory.

    A sequence holds ``s, y, eps, wfs`` (float64); a batch its history tensor and the targets.
    """
    scenario.require_stream_frames(data.sequence_frames, f"data.sequence_frames={data.sequence_frames}",
                                   data.realisations)
    n_act = scenario.grid.n_actuators
    require_memory(8 * data.realisations * n_act * (4 * data.sequence_frames + data.batch_frames * (spec.n_taps + 1)),
                   f"training data with data.sequence_frames={data.sequence_frames}, data.realisations="
                   f"{data.realisations}, data.batch_frames={data.batch_frames} and {n_act} actuators")


def require_target(scenario: Scenario, data: DataConfig) -> None:
    """Refuse, in one line, a ``data.target`` that ``scenario`` cannot give: ``dm_fit`` needs a Shack-Hartmann (the
    zonal sensor's ``s`` is the turbulence at the actuators, with no aliasing: it is already the DM's view of it)."""
    require(data.target == "measured" or scenario.sensor.is_shack_hartmann,
            f"data.target={data.target!r} is for a Shack-Hartmann scenario (sensor.kind: shack_hartmann): the zonal "
            "sensor has no aliasing, its s is already what the DM can fit; use data.target: measured")


def open_loop_recorded(scenario: Scenario, data: DataConfig) -> bool:
    """Whether open-loop (POL) training data is recorded in the closed loop, by the dithered integrator, rather than
    read from the turbulence with no correction: with ``data.plant_range`` (the drawn plant's mismatch) and with a
    pyramid, whose reading is not linear in the phase. About the uncorrected turbulence its optical gains are far
    below those about a closed loop's residual (docs/findings.md), so a filter fitted to open-loop readings would
    scale its prediction up by their ratio in the loop, whose POL values
    ``wfs + y`` are mostly the commands it sent; recorded in the loop, compensated as the loop compensates, they are
    the POL values the filter reads there."""
    return bool(data.plant_range) or scenario.sensor.is_pyramid


def sequence_plant(plant: Plant, data: DataConfig, name: str) -> Plant:
    """The plant sequence ``name`` (``"<stream>:<index>"``) is simulated in: ``plant`` itself without
    ``data.plant_range``, else ``plant`` with each ranged field drawn uniformly from its interval, from a generator
    seeded by ``data.seed`` and ``name`` (the same draws whatever the workers or the order of the sequences)."""
    if not data.plant_range:
        return plant
    rng = np.random.default_rng(stream_seed(data.seed, name, 4))
    return plant.with_errors(**{field: low + (high - low) * rng.random()
                                for field, (low, high) in data.plant_range.items()})


class SimulatedTelemetry(IterableDataset):
    """Yields ``(history, target)`` batches of simulated telemetry, ``(samples, K, taps)`` and ``(samples, K)``.

    Telemetry comes in *sequences* of ``data.sequence_frames`` frames, each from its own turbulence realisation
    (stream ``"<stream>:<index>"``), so sequence ``i`` is the same whatever the number of workers; worker ``w``
    of ``W`` takes the sequences ``i = w, w + W, ...``: two workers never produce the same frames.

    Open-loop data is the turbulence as a perfect pseudo-open-loop reconstruction would give it, plus the WFS
    noise of the scenario; through a pyramid it is recorded in the loop by ``data_controller`` and reconstructed
    (:func:`open_loop_recorded`). Closed-loop data is recorded by running ``data_controller`` in the scenario's plant.

    With ``data.plant_range`` each sequence has its own plant (:func:`sequence_plant`): closed-loop data is recorded
    in it, and so is open-loop data (by ``data_controller``), whose POL values are then reconstructed with the DM gain
    the filter believes (``dm_gain_model``, 1), carrying the mismatch of the drawn plant; targets are the commands
    that cancel the turbulence in the drawn plant (``-s / g`` with its DM gain ``g``) unless ``target_dm_gain`` is
    given.

    With ``data.target: dm_fit`` (a Shack-Hartmann scenario) the targets cancel the DM's fit of the true phase
    ``P F phi`` in place of the loop's ``s = R S phi``: same sign, gain and (fractional) delay, same histories.

    Parameters
    ----------
    scenario : Scenario
        Where the data is recorded.
    spec : HistorySpec
        History kind, length and delay.
    frames : int
        Frames of this stream (rounded up to whole sequences).
    stream : str
        Stream name; training and validation use different names.
    data : DataConfig
        Seed, sequence and batch lengths, realisations.
    data_controller : Controller, optional
        Records closed-loop data (required for closed-loop histories). A controller with a ``reseed(int)``
        method gets a seed of its own per sequence (its dither).
    target_dm_gain : float, optional
        Targets are ``-s(n) / target_dm_gain`` (averaged over two frames for a fractional delay,
        :func:`eofnn.data.history.targets`); by default the gain of the scenario's DM for closed-loop data
        (the command that really cancels the turbulence in the plant that recorded it) and 1 for open-loop data.
    """

    def __init__(self, scenario: Scenario, spec: HistorySpec, frames: int, stream: str = "train",
                 data: DataConfig | None = None, data_controller: Controller | None = None,
                 target_dm_gain: float | None = None) -> None:
        super().__init__()
        data = data or DataConfig()
        check_value("frames", frames, COUNT)
        require(data.sequence_frames > spec.first_frame + spec.target_lead,
                f"data.sequence_frames={data.sequence_frames!r} is invalid: it must exceed the history span "
                f"{spec.first_frame + spec.target_lead}")
        if spec.kind == "closed_loop":
            require(data_controller is not None, "closed-loop data needs a data_controller")
        elif open_loop_recorded(scenario, data):
            require(data_controller is not None, "open-loop data with data.plant_range or a pyramid needs a "
                                                 "data_controller (the loop that records its POL values)")
        require_training_memory(scenario, spec, data)
        require_target(scenario, data)
        self.scenario, self.spec, self.stream, self.data = scenario, spec, stream, data
        self.n_sequences = -(-frames // data.sequence_frames)
        self.data_controller = data_controller
        #: Targets of a ranged sequence use its own drawn DM gain unless a gain was given.
        self.ranged_targets = target_dm_gain is None and bool(data.plant_range)
        if target_dm_gain is None:
            target_dm_gain = scenario.plant.dm_gain if spec.kind == "closed_loop" else 1.0
        check_value("target_dm_gain", target_dm_gain, POSITIVE)
        self.target_dm_gain = target_dm_gain
        #: DM gain of the open-loop POL reconstruction of data recorded in a drawn plant (the filter's belief).
        self.dm_gain_model = 1.0

    def telemetry(self, index: int) -> dict[str, torch.Tensor]:
        """Arrays ``(R, frames, K)`` of sequence ``index``: ``s`` and ``s_hat`` (open loop) or ``s, y, wfs``; ``s`` is
        the turbulence the targets cancel (``data.target``: the loop's, or the DM's fit of the true phase)."""
        name, seed = f"{self.stream}:{index}", self.data.seed
        turbulence = self.scenario.turbulence(seed, name, self.data.realisations)
        arrays = self._recorded(turbulence, index)
        if self.data.target == "dm_fit":  # the same cached chunks: P F phi beside the R S phi the loop saw
            arrays["s"] = turbulence.products(0, arrays["s"].shape[-2])["fit"]
            turbulence.release()
        return arrays

    def _recorded(self, turbulence, index: int) -> dict[str, torch.Tensor]:
        """What :meth:`telemetry` holds before ``data.target`` picks the turbulence of the targets."""
        name, seed = f"{self.stream}:{index}", self.data.seed
        plant = self.plant(index)
        if self.spec.kind == "open_loop" and not open_loop_recorded(self.scenario, self.data):
            if hasattr(turbulence, "open_loop"):  # a Shack-Hartmann's: reconstructed slopes, aliasing and noise
                s, s_hat = turbulence.open_loop(0, self.data.sequence_frames, plant, torch_generator(seed, name, 1))
                return {"s": s, "s_hat": s_hat}
            s = turbulence.frames(0, self.data.sequence_frames)
            s_hat = s
            if getattr(turbulence, "sensor", None) is not None:  # a registered sensor (sensor.kind): what it measures
                return {"s": s, "s_hat": _registered_open_loop(turbulence, plant, s, torch_generator(seed, name, 1))}
            if plant.wfs_noise_nm > 0:
                gen = torch_generator(seed, name, 1)
                s_hat = s + plant.wfs_noise_nm / plant.wfs_gain * torch.randn(s.shape, generator=gen, dtype=s.dtype)
            return {"s": s, "s_hat": s_hat}
        controller = copy.deepcopy(self.data_controller)
        if callable(getattr(controller, "reseed", None)):
            controller.reseed(int_seed(seed, name, 2))
        result = record_loop(turbulence, plant, controller, self.data.sequence_frames,
                             noise_seed=int_seed(seed, name, 3), record=("s", "y", "wfs"), recorder="the data controller",
                             where=f" while recording training sequence {name!r}",
                             hint="lower data.integrator_gain or data.dither_nm, or use fewer data.refit_rounds")
        if self.spec.kind == "open_loop":
            s_hat = pseudo_open_loop(result.telemetry.wfs, result.telemetry.y, self.dm_gain_model,
                                     self.spec.delay_fraction)
            return {"s": result.telemetry.s, "s_hat": s_hat}
        return {"s": result.telemetry.s, "y": result.telemetry.y, "wfs": result.telemetry.wfs}

    def plant(self, index: int) -> Plant:
        """The plant sequence ``index`` is simulated in (:func:`sequence_plant`)."""
        return sequence_plant(self.scenario.plant, self.data, f"{self.stream}:{index}")

    def target_gain(self, index: int) -> float:
        """The DM gain of sequence ``index``'s targets: ``target_dm_gain``, or the drawn plant's DM gain for ranged
        data (the command that really cancels the turbulence in the plant that recorded it)."""
        return self.plant(index).dm_gain if self.ranged_targets else self.target_dm_gain

    def _history(self, arrays: dict[str, torch.Tensor], gain: float) -> tuple[torch.Tensor, torch.Tensor]:
        if self.spec.kind == "open_loop":
            history = build_history(self.spec, s=arrays["s_hat"])
        else:
            history = build_history(self.spec, y=arrays["y"], wfs=arrays["wfs"])
        return history, targets(arrays["s"], self.spec, gain)

    def sequence(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """History and target tensors of sequence ``index``: ``(R, samples, K, taps)`` and ``(R, samples, K)``."""
        return self._history(self.telemetry(index), self.target_gain(index))

    def __iter__(self) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        info = get_worker_info()
        worker, n_workers = (info.id, info.num_workers) if info is not None else (0, 1)
        span, batch, lead = self.spec.first_frame, self.data.batch_frames, self.spec.target_lead
        for index in range(worker, self.n_sequences, n_workers):
            arrays, gain = self.telemetry(index), self.target_gain(index)
            n_frames = arrays["s"].shape[1]
            # Histories are built one batch of frames at a time: a long sequence never needs its whole
            # (frames x K x taps) history tensor in memory. A fractional delay's target reads `lead` frames ahead.
            for first in range(span, n_frames - lead, batch):
                window = {k: v[:, first - span: first + batch + lead] for k, v in arrays.items()}
                x, t = self._history(window, gain)
                yield x.reshape(-1, *x.shape[2:]), t.reshape(-1, x.shape[-2])


class LoopDataModule(L.LightningDataModule):
    """Training and held-out validation streams of simulated telemetry for one scenario and history.

    Parameters
    ----------
    scenario, spec : Scenario, HistorySpec
        Where the data is recorded, and the history (kind, length, delay), as for :class:`SimulatedTelemetry`.
    data : DataConfig
        Frames, sequences, batches, seed and workers.
    data_controller : Controller, optional
        Records closed-loop data (required for closed-loop histories).
    """

    def __init__(self, scenario: Scenario, spec: HistorySpec, data: DataConfig | None = None,
                 data_controller: Controller | None = None, target_dm_gain: float | None = None) -> None:
        super().__init__()
        self.scenario, self.spec, self.data = scenario, spec, data or DataConfig()
        self.data_controller, self.target_dm_gain = data_controller, target_dm_gain

    def dataset(self, stream: str, frames: int) -> SimulatedTelemetry:
        sequence_frames = min(self.data.sequence_frames, max(frames, self.spec.first_frame + self.spec.target_lead + 1))
        data = replace(self.data, sequence_frames=sequence_frames)
        return SimulatedTelemetry(self.scenario, self.spec, frames, stream, data, self.data_controller,
                                  self.target_dm_gain)

    def train_dataloader(self) -> DataLoader:
        return DataLoader(self.dataset("train", self.data.frames), batch_size=None, num_workers=self.data.num_workers)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.dataset("validation", self.data.val_frames), batch_size=None, num_workers=0)


def _registered_open_loop(turbulence, plant, s: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """What a registered sensor (:func:`~eofnn.sim.loop.kernel.register_sensor`, the scenario's ``sensor.kind``)
    measures of the open-loop turbulence ``s`` ``(R, frames, K)``: the residual is ``s`` itself (no DM acts)."""
    from eofnn.sim.loop.sensing import loop_measurement

    measurement = loop_measurement(turbulence, plant)
    measurement.reset()
    noise = None
    if measurement.noisy:
        noise = measurement.noise(torch.randn((*s.shape[:2], measurement.noise_size), generator=generator,
                                              dtype=s.dtype))
    zeros = torch.zeros_like(s)
    return measurement.measure(s, s, zeros, zeros, noise)
