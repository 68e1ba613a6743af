"""Telemetry simulated on the fly, cut into history tensors: the training data of every predictor."""

from __future__ import annotations

import copy
import warnings
from collections.abc import Iterator

import lightning as L
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from eofnn.data.history import HistorySpec, build_history, targets
from eofnn.errors import DivergedError, require
from eofnn.models.controllers import Dithered, Integrator
from eofnn.sim.loop import run_loop
from eofnn.sim.scenario import Scenario
from eofnn.sim.turbulence import stream_seed
from eofnn.training.ridge import CollinearityWarning


class SimulatedTelemetry(IterableDataset):
    """Yields ``(history, target)`` batches of simulated telemetry, ``(samples, K, taps)`` and ``(samples, K)``.

    Telemetry comes in *sequences* of ``sequence_frames`` frames, each from its own turbulence realisation
    (stream ``"<stream>:<index>"``), so sequence ``i`` is the same whatever the number of workers; worker ``w``
    of ``W`` takes the sequences ``i = w, w + W, ...``: two workers never produce the same frames.

    Open-loop data is the turbulence as a perfect pseudo-open-loop reconstruction would give it, plus the WFS
    noise of the scenario. Closed-loop data is recorded by running ``data_controller`` in the scenario's plant.

    Parameters
    ----------
    scenario : Scenario
        Where the data is recorded.
    spec : HistorySpec
        History kind, length and delay.
    n_frames : int
        Frames per epoch (rounded up to whole sequences).
    seed : int
        Master seed.
    stream : str
        Stream name; training and validation use different names.
    sequence_frames : int
        Frames per independent sequence.
    batch_frames : int
        Frames per yielded batch (times ``n_realisations`` samples).
    n_realisations : int
        Realisations simulated side by side per sequence.
    data_controller : Controller, optional
        Controller that records closed-loop data (required for closed-loop histories).
    target_dm_gain : float, optional
        Targets are ``-s(n) / target_dm_gain``; by default the gain of the scenario's DM for closed-loop data
        (the command that really cancels the turbulence in the plant that recorded it) and 1 for open-loop data.
    """

    def __init__(self, scenario: Scenario, spec: HistorySpec, n_frames: int, seed: int = 0, stream: str = "train",
                 sequence_frames: int = 10000, batch_frames: int = 256, n_realisations: int = 1,
                 data_controller=None, target_dm_gain: float | None = None) -> None:
        super().__init__()
        require(n_frames >= 1, f"n_frames={n_frames!r} is invalid: it must be >= 1")
        require(sequence_frames > spec.first_frame,
                f"sequence_frames={sequence_frames!r} is invalid: it must exceed the history span {spec.first_frame}")
        require(batch_frames >= 1, f"batch_frames={batch_frames!r} is invalid: it must be >= 1")
        if spec.kind == "closed_loop":
            require(data_controller is not None, "closed-loop data needs a data_controller")
            if isinstance(data_controller, Dithered) and data_controller.amplitude_nm == 0:
                warnings.warn("closed-loop data recorded without excitation (dither amplitude 0): the controller "
                              "law ties y to past eps, so the regressors are collinear; set a dither > 0",
                              CollinearityWarning, stacklevel=2)
        self.scenario, self.spec, self.seed, self.stream = scenario, spec, seed, stream
        self.sequence_frames, self.batch_frames, self.n_realisations = sequence_frames, batch_frames, n_realisations
        self.n_sequences = -(-n_frames // sequence_frames)
        self.data_controller = data_controller
        if target_dm_gain is None:
            target_dm_gain = scenario.plant.dm_gain if spec.kind == "closed_loop" else 1.0
        self.target_dm_gain = target_dm_gain

    def telemetry(self, index: int) -> dict[str, torch.Tensor]:
        """Arrays ``(R, frames, K)`` of sequence ``index``: ``s`` and ``s_hat`` (open loop) or ``s, y, wfs``."""
        name = f"{self.stream}:{index}"
        turbulence = self.scenario.turbulence(self.seed, name, self.n_realisations)
        plant = self.scenario.plant
        if self.spec.kind == "open_loop":
            s = turbulence.frames(0, self.sequence_frames)
            s_hat = s
            if plant.wfs_noise_nm > 0:
                gen = torch.Generator().manual_seed(int(stream_seed(self.seed, name, 1).generate_state(1)[0]))
                s_hat = s + plant.wfs_noise_nm / plant.wfs_gain * torch.randn(s.shape, generator=gen, dtype=s.dtype)
            return {"s": s, "s_hat": s_hat}
        controller = copy.deepcopy(self.data_controller)
        if isinstance(controller, Dithered):
            controller.seed = int(stream_seed(self.seed, name, 2).generate_state(1)[0])
        result = run_loop(turbulence, plant, controller, self.sequence_frames, record=("s", "y", "wfs"),
                          noise_seed=int(stream_seed(self.seed, name, 3).generate_state(1)[0]), progress=False)
        if result.diverged:
            raise DivergedError(f"the data controller diverged at frame {result.diverged_frame} while recording "
                                f"training sequence {name!r}: lower integrator_gain or dither_nm, or use fewer "
                                "refit_rounds")
        return {"s": result.telemetry.s, "y": result.telemetry.y, "wfs": result.telemetry.wfs}

    def _history(self, arrays: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        if self.spec.kind == "open_loop":
            history = build_history(self.spec, s=arrays["s_hat"])
        else:
            history = build_history(self.spec, y=arrays["y"], wfs=arrays["wfs"])
        return history, targets(arrays["s"], self.spec, self.target_dm_gain)

    def sequence(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """History and target tensors of sequence ``index``: ``(R, samples, K, taps)`` and ``(R, samples, K)``."""
        return self._history(self.telemetry(index))

    def __iter__(self) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        info = get_worker_info()
        worker, n_workers = (info.id, info.num_workers) if info is not None else (0, 1)
        span = self.spec.first_frame
        for index in range(worker, self.n_sequences, n_workers):
            arrays = self.telemetry(index)
            n_frames = arrays["s"].shape[1]
            # Histories are built one batch of frames at a time: a long sequence never needs its whole
            # (frames x K x taps) history tensor in memory.
            for first in range(span, n_frames, self.batch_frames):
                window = {k: v[:, first - span: first + self.batch_frames] for k, v in arrays.items()}
                x, t = self._history(window)
                yield x.reshape(-1, *x.shape[2:]), t.reshape(-1, x.shape[-2])


def default_data_controller(gain: float = 0.5, leak: float = 0.0, dither_nm: float = 10.0, seed: int = 0):
    """Integrator plus white dither: the data controller that records closed-loop training data."""
    return Dithered(Integrator(gain, leak), dither_nm, seed)


class LoopDataModule(L.LightningDataModule):
    """Training and held-out validation streams of simulated telemetry for one scenario and history.

    Parameters
    ----------
    scenario : Scenario
        Where the data is recorded.
    spec : HistorySpec
        History kind, length and delay.
    train_frames, val_frames : int
        Frames per training epoch and in the fixed validation stream.
    sequence_frames, batch_frames, n_realisations : int
        See :class:`SimulatedTelemetry`.
    seed : int
        Master seed (validation uses its own stream of it).
    data_controller : Controller, optional
        Records closed-loop data; :func:`default_data_controller` if None and the history is closed-loop.
    num_workers : int
        DataLoader worker processes.
    """

    def __init__(self, scenario: Scenario, spec: HistorySpec, train_frames: int = 20000, val_frames: int = 2000,
                 sequence_frames: int = 10000, batch_frames: int = 256, n_realisations: int = 1, seed: int = 0,
                 data_controller=None, num_workers: int = 0, target_dm_gain: float | None = None) -> None:
        super().__init__()
        if data_controller is None and spec.kind == "closed_loop":
            data_controller = default_data_controller()
        self.scenario, self.spec, self.seed = scenario, spec, seed
        self.train_frames, self.val_frames = train_frames, val_frames
        self.sequence_frames, self.batch_frames, self.n_realisations = sequence_frames, batch_frames, n_realisations
        self.data_controller, self.num_workers, self.target_dm_gain = data_controller, num_workers, target_dm_gain

    def dataset(self, stream: str, n_frames: int) -> SimulatedTelemetry:
        sequence_frames = min(self.sequence_frames, max(n_frames, self.spec.first_frame + 1))
        return SimulatedTelemetry(self.scenario, self.spec, n_frames, self.seed, stream, sequence_frames,
                                  self.batch_frames, self.n_realisations, self.data_controller, self.target_dm_gain)

    def train_dataloader(self) -> DataLoader:
        return DataLoader(self.dataset("train", self.train_frames), batch_size=None, num_workers=self.num_workers)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.dataset("validation", self.val_frames), batch_size=None, num_workers=0)
