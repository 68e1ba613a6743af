"""The closed-loop runner: a controller against turbulence through the plant, batched over realisations."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from dataclasses import dataclass

from tqdm.auto import tqdm

from eofnn.errors import DivergedError, require
from eofnn.lazy import lazy_module
from eofnn.seeding import torch_generator
from eofnn.sim.atmosphere.turbulence import Turbulence
from eofnn.sim.loop.kernel import Controller, Loop, LoopInput
from eofnn.sim.loop.plant import Plant, PlantModel
from eofnn.sim.loop.sensing import loop_sensing
from eofnn.telemetry.record import Telemetry
from eofnn.validation import COUNT, check_value

torch = lazy_module("torch")

__all__ = ["Controller", "LoopInput", "LoopResult", "record_loop", "run_loop"]


@dataclass
class LoopResult:
    """Outcome of :func:`run_loop`.

    Attributes
    ----------
    telemetry : Telemetry
        Recorded arrays (those asked for), ``(batch, frames, n_actuators)``, up to the last frame run.
    residual_rms_nm : Tensor
        ``(batch, frames)`` spatial RMS of the true residual ``eps``.
    turbulence_rms_nm : Tensor
        ``(batch, frames)`` spatial RMS of the turbulence ``s``.
    pupil_residual_rms_nm : Tensor or None
        ``(batch, frames)`` piston-removed RMS of the residual over the pupil on the sensor's fine grid, fitting error
        included (a Shack-Hartmann scenario, :mod:`eofnn.sim.loop.sensing`); ``None`` for the zonal sensor, whose
        residual exists only at the actuators (``residual_rms_nm``).
    diverged : bool
        Whether the loop diverged (non-finite residual or one above ``divergence_factor`` x the turbulence).
    diverged_frame : int or None
        First frame at which it diverged.
    """

    telemetry: Telemetry
    residual_rms_nm: torch.Tensor
    turbulence_rms_nm: torch.Tensor
    diverged: bool = False
    diverged_frame: int | None = None
    pupil_residual_rms_nm: torch.Tensor | None = None


def run_loop(
    turbulence: Turbulence,
    plant: Plant,
    controller: Controller,
    n_frames: int,
    *,
    noise_seed: int = 0,
    record: tuple[str, ...] = ("s", "y", "eps", "wfs"),
    chunk_frames: int = 1024,
    divergence_factor: float = 10.0,
    progress: bool | None = None,
    on_chunk: Callable[[int, dict[str, torch.Tensor]], None] | None = None,
    sensor=None,
) -> LoopResult:
    """Close the loop for ``n_frames`` frames.

    Per frame ``n`` (:class:`~eofnn.sim.loop.kernel.Loop`'s step, in place): the controller gets the WFS measurement
    of ``eps(n - d)`` and returns ``y(n)``; the DM applies it through the plant; ``eps(n) = s(n) + DM(y(n))``; the WFS
    measures ``eps(n)``. For a fractional delay ``d + f`` (:mod:`eofnn.delay`) the DM term is the time average
    ``(1 - f) DM(y(n)) + f DM(y(n - 1))``: telemetry's ``y`` is the command computed for frame ``n``, its ``eps`` and
    ``wfs`` include the averaged DM.
    A Shack-Hartmann scenario's turbulence (:class:`~eofnn.sim.loop.sensing.ShackHartmannTurbulence`) measures through
    slopes and a reconstructor and scores the residual over the pupil too (:mod:`eofnn.sim.loop.sensing`).

    Parameters
    ----------
    turbulence : Turbulence
        Source of ``s(n)``; its realisations are the batch.
    plant : Plant
        Delay and model errors.
    controller : Controller
        Computes the commands.
    n_frames : int
        Frames to run.
    noise_seed : int
        Seed of the WFS noise.
    record : tuple of str
        Which of ``s, y, eps, wfs`` to keep in the returned telemetry (empty for long runs: RMS is always kept);
        ``slopes`` (a Shack-Hartmann scenario only) also keeps the sensor's slopes, ``(batch, frames, 2 n_sub)`` nm of
        OPD difference across each subaperture, with its interaction matrix and reconstructor and a note of the
        sensor in the telemetry's config (:mod:`eofnn.sim.loop.sensing`).
    chunk_frames : int
        Turbulence frames generated at a time.
    divergence_factor : float
        A residual RMS above this times the turbulence RMS (or non-finite) stops the run as diverged.
    progress : bool or None
        Show a progress bar; ``None`` shows it only when stderr is a terminal.
    on_chunk : callable, optional
        Called as ``on_chunk(first_frame, arrays)`` after each chunk with all four arrays of that chunk; in a
        Shack-Hartmann (or pyramid) scenario ``arrays["fit"]`` is also the chunk's ``P F phi``, the DM's fit of the
        true phase on the modes the sensor sees, and ``arrays["pupil_residual"](frame)`` gives the residual over the
        pupil's fine points at a frame of the chunk that is a multiple of :data:`~eofnn.sim.loop.sensing.PHASE_EVERY`.
    sensor : LoopSensor or str, optional
        A sensor of the actuator-grid turbulence in place of the zonal one: a
        :class:`~eofnn.sim.loop.kernel.LoopSensor`, or the name it was registered under
        (:func:`~eofnn.sim.loop.kernel.register_sensor`); ``None``: the scenario's.
    """
    check_value("n_frames", n_frames, COUNT)
    unknown = set(record) - {"s", "y", "eps", "wfs", "slopes"}
    require(not unknown, f"record={sorted(unknown)!r} is invalid: allowed are s, y, eps, wfs, slopes")
    grid = turbulence.grid
    model = PlantModel(plant, grid, frame_rate_hz=getattr(turbulence, "frame_rate_hz", None))
    sensing = loop_sensing(turbulence, model, "slopes" in record, sensor)
    batch, n_act = turbulence.n_realisations, grid.n_actuators
    dtype = torch.float64
    loop = Loop(model, sensing.measurement(), controller)
    loop.reset(batch, n_act, dtype)
    generator = torch_generator(noise_seed, "wfs-noise")
    # Per-chunk arrays are allocated only for what leaves the loop; eps (for the RMS) otherwise reuses one buffer.
    kept_arrays = set(record) | ({"y", "eps", "wfs"} if on_chunk is not None else set())
    eps_scratch = None
    kept: dict[str, list[torch.Tensor]] = {name: [] for name in record}
    residual_rms, turbulence_rms, pupil_rms = [], [], []
    dm_chunk = None
    diverged_frame = None
    if progress is None:
        progress = sys.stderr.isatty()
    bar = tqdm(total=n_frames, unit="frame", disable=not progress, leave=False)
    try:
        for first, s_chunk in sensing.chunks(n_frames, chunk_frames, generator):
            t = s_chunk.shape[1]
            if sensing.pupil and (dm_chunk is None or dm_chunk.shape[1] < t):
                dm_chunk = torch.empty(batch, t, n_act, dtype=dtype)
            arrays = {name: torch.empty(batch, t, n_act, dtype=dtype) for name in ("y", "eps", "wfs")
                      if name in kept_arrays}
            if "slopes" in record:
                arrays["slopes"] = torch.empty(batch, t, sensing.n_slopes, dtype=dtype)
            if "eps" not in arrays:
                if eps_scratch is None or eps_scratch.shape[1] < t:
                    eps_scratch = torch.empty(batch, t, n_act, dtype=dtype)
                arrays["eps"] = eps_scratch[:, :t]
            y_out, eps_out, wfs_out, slopes_out = arrays.get("y"), arrays["eps"], arrays.get("wfs"), arrays.get("slopes")
            arrays["s"] = s_chunk
            if sensing.pupil and on_chunk is not None:  # P F phi beside s for on_chunk: the residual against the
                # DM's fit of the true phase is eps - s + fit
                arrays["fit"] = sensing.fit()
            for i in range(t):
                s_n = s_chunk[:, i]
                step = loop.step(first + i, s_n, sensing.noise(i, s_n, generator), out=eps_out[:, i],
                                 sensed=sensing.sensed(i))
                if dm_chunk is not None:
                    dm_chunk[:, i] = step.dm
                if y_out is not None:
                    y_out[:, i] = step.y
                if wfs_out is not None:
                    wfs_out[:, i] = step.wfs
                if slopes_out is not None:
                    slopes_out[:, i] = sensing.slopes(i, step.dm)
            rms = arrays["eps"].pow(2).mean(-1).sqrt()
            turb = s_chunk.pow(2).mean(-1).sqrt()
            bad = ~torch.isfinite(rms) | (rms > divergence_factor * turb)
            if bad.any():
                stop = int(bad.any(0).nonzero()[0])
                diverged_frame = first + stop
                arrays = {k: v[:, :stop] for k, v in arrays.items()}
                rms, turb = rms[:, :stop], turb[:, :stop]
            if sensing.pupil:
                pupil_rms.append(sensing.pupil_rms(dm_chunk[:, :rms.shape[1]]))
            residual_rms.append(rms)
            turbulence_rms.append(turb)
            for name in record:
                kept[name].append(arrays[name])
            if on_chunk is not None and arrays["s"].shape[1]:
                if sensing.pupil:  # a Shack-Hartmann's residual over the pupil at frames where its phase is kept
                    arrays["pupil_residual"] = functools.partial(_pupil_residual, sensing, dm_chunk, first)
                on_chunk(first, arrays)
            bar.update(t)
            if diverged_frame is not None:
                break
    finally:
        bar.close()
    matrices, note = sensing.space() if "slopes" in record else ({}, None)
    telemetry = Telemetry(
        **{name: torch.cat(kept[name], 1) for name in record},
        delay_frames=plant.delay_frames,
        config={"plant": plant.to_dict(), **({"sensor": note} if note else {})},
        positions_m=torch.as_tensor(grid.positions_m),
        **matrices,
    )
    return LoopResult(
        telemetry=telemetry,
        residual_rms_nm=torch.cat(residual_rms, 1),
        turbulence_rms_nm=torch.cat(turbulence_rms, 1),
        diverged=diverged_frame is not None,
        diverged_frame=diverged_frame,
        pupil_residual_rms_nm=torch.cat(pupil_rms, 1) if pupil_rms else None,
    )


def _pupil_residual(sensing, dm_chunk: torch.Tensor, first: int, frame: int) -> torch.Tensor:
    """``(batch, n_pupil)`` residual over the pupil at ``frame`` of the chunk starting at ``first``."""
    return sensing.pupil_residual(frame, dm_chunk[:, frame - first])


def record_loop(turbulence: Turbulence, plant: Plant, controller: Controller, n_frames: int, *, noise_seed: int,
                record: tuple[str, ...] = ("y", "wfs"), progress: bool | None = False,
                recorder: str = "the recording integrator", where: str = "",
                hint: str = "lower data.integrator_gain or data.dither_nm") -> LoopResult:
    """Telemetry recorded while ``controller`` holds the loop (:func:`run_loop`), refused when the loop diverged with
    one line: ``"{recorder} diverged at frame N{where}: {hint}"``."""
    result = run_loop(turbulence, plant, controller, n_frames, noise_seed=noise_seed, record=record, progress=progress)
    if result.diverged:
        raise DivergedError(f"{recorder} diverged at frame {result.diverged_frame}{where}: {hint}")
    return result
