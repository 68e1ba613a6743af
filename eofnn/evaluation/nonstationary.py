"""Metrics of non-stationary runs: how long each controller takes to re-converge after a change.

A *change* is an entry of ``atmosphere.changes`` (it ends at ``at_s + ramp_s``) or the plant's DM gain drift (it
ends at ``stop_s``). After a change ends, its *segment* runs to the start of the next change (or the end of the
run). The reference level of a segment is the lowest median RMS over the segment's second half among the
controllers of the scenario that did not diverge: the best any of them settles to in the new conditions (a filter
trained for them, when the config gives one as a checkpoint, or an adapted filter). A controller has re-converged
``n`` frames after the change's end when the running median of its residual RMS over the last
:data:`WINDOW_S` (its window wholly after the end) first comes within 10% of that level and stays there for
:data:`HOLD_S` (or to the segment's end); ``n`` counts the frames of data since the end, so
``WINDOW_S * frame_rate`` is the smallest value. For comparison, ``median_rms_before_nm`` is the median over the
second half of the segment before the change (from the previous change's end, or frame 0, to this one's start).
The RMS is the realisations' mean at each frame.
"""

from __future__ import annotations

import torch

from eofnn.sim.scenario import Change

#: Running-median window of the residual RMS, in seconds.
WINDOW_S = 0.2
#: Time the running median must stay within the tolerance, in seconds.
HOLD_S = 1.0
#: Re-converged: within this fraction above the reference level.
TOLERANCE = 0.1


def running_median(rms: torch.Tensor, window: int) -> torch.Tensor:
    """Median of each ``window`` consecutive values: entry ``i`` covers ``rms[i : i + window]``."""
    return rms.unfold(0, window, 1).median(-1).values


def reconvergence(rms_by_controller: dict[str, list[float] | None], changes: list[Change],
                  frame_rate_hz: float) -> dict[str, list[dict]]:
    """Per controller, one entry per change: the reference level, its own settled median and re-convergence time.

    Parameters
    ----------
    rms_by_controller : dict
        Controller name -> residual RMS per frame (nm) from frame 0, or ``None`` if it diverged.
    changes : list of Change
        The scenario's changes (:meth:`~eofnn.sim.scenario.Scenario.changes`).
    frame_rate_hz : float
        Frames per second.

    Returns
    -------
    dict
        Controller name -> list of ``{change, end_s, reference, reference_rms_nm, median_rms_before_nm,
        median_rms_after_nm, reconvergence_frames, reconvergence_s}`` (``None`` where it does not apply: a diverged controller, a
        segment shorter than the window, a controller that never re-converged).
    """
    window, hold = max(1, round(WINDOW_S * frame_rate_hz)), max(1, round(HOLD_S * frame_rate_hz))
    series = {name: None if rms is None else torch.as_tensor(rms, dtype=torch.float64)
              for name, rms in rms_by_controller.items()}
    out: dict[str, list[dict]] = {name: [] for name in series}
    for j, change in enumerate(changes):
        later = [c.start_frame for c in changes[j + 1:] if c.start_frame >= change.end_frame]
        stop = min(later, default=None)
        settled = {}
        for name, rms in series.items():
            if rms is None:
                continue
            end = len(rms) if stop is None else min(stop, len(rms))
            if end - change.end_frame >= window:
                settled[name] = float(rms[(change.end_frame + end) // 2: end].median())
        first = max([c.end_frame for c in changes[:j] if c.end_frame <= change.start_frame], default=0)
        before = {name: float(rms[(first + change.start_frame) // 2: change.start_frame].median())
                  for name, rms in series.items()
                  if rms is not None and len(rms) >= change.start_frame > (first + change.start_frame) // 2}
        reference = min(settled, key=settled.get) if settled else None
        level = settled.get(reference)
        for name, rms in series.items():
            frames = None
            if name in settled:
                end = len(rms) if stop is None else min(stop, len(rms))
                ok = running_median(rms[change.end_frame: end], window) <= (1 + TOLERANCE) * level
                need = min(hold, len(ok))
                good = ok.to(torch.int64).cumsum(0)
                runs = good[need - 1:] - torch.cat([good.new_zeros(1), good[:-need]])  # ok frames in [i, i + need)
                hits = torch.nonzero(runs == need).flatten()
                frames = None if len(hits) == 0 else int(hits[0]) + window
            out[name].append({
                "change": change.name,
                "end_s": change.end_frame / frame_rate_hz,
                "reference": reference,
                "reference_rms_nm": level,
                "median_rms_before_nm": before.get(name),
                "median_rms_after_nm": settled.get(name),
                "reconvergence_frames": frames,
                "reconvergence_s": None if frames is None else frames / frame_rate_hz,
            })
    return out
