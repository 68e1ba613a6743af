"""What an experiment's contenders share instead of closing the same loops again.

Two loops are the same loop when the controller, the plant and the streams (the turbulence and the noise) are: every
number they produce is then the same, bit for bit on one CPU. :class:`~eofnn.evaluation.experiment.Experiment` shares

1. a best-gain integrator's gain scan: a guard's scan (``fallback.gains``, ``frames``, ``seed``,
   :func:`~eofnn.evaluation.fallback.decide_fallback`) is the integrator contender's when both name the same gains,
   frames, seed, leak, refinement, settling and divergence factor in the same scenario (:meth:`LoopSharing.scan`);
2. a contender's scored loops: a guarded contender whose guard deploys the predictor whole runs the very controller
   of the contender it shares its training with (same config but its fallback, same trained predictor), so its test
   loop and its error budget's loops are that contender's (:meth:`LoopSharing.scored`, keyed by :func:`loop_key`);
3. the fitting error of a test stream, a property of the turbulence alone: once per stream (:meth:`LoopSharing.fitting`).

The slope noise every loop on a stream draws again is kept by the sensing
(:func:`eofnn.sim.loop.readings.reconstructed_noise`). ``LoopSharing(enabled=False)`` runs everything again (what the
tests compare against); :attr:`LoopSharing.reused` counts what was shared.
"""

from __future__ import annotations

import copy
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from typing import Any


def loop_key(config, predictor: Any, scenario_name: str, deployed: str | None = None) -> tuple | None:
    """What names the loops a contender is scored on in ``scenario_name``: the config its controller is built from
    (its fallback left out) and the trained predictor (or model) it runs, by identity; ``deployed``: what its guard
    deploys (``None``: unguarded). ``None`` where no other contender can share them: a guard that deploys the
    integrator or the composite (their controllers differ from every contender's config), or a controller that
    adapts while it runs."""
    if deployed not in (None, "predictor"):
        return None
    adaptation = getattr(config, "adaptation", None)
    if adaptation is not None and adaptation.method != "none":
        return None
    return scenario_name, repr(replace(config, fallback=type(config.fallback)())), id(predictor)


class LoopSharing:
    """The scans, scored loops and fitting errors of one experiment, kept for the contenders that run the same loops
    (module docstring). ``enabled=False``: nothing is kept, every loop runs."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        #: What was shared instead of run: ``gain_scan``, ``scored`` (a contender's loops), ``fitting``.
        self.reused: Counter = Counter()
        self._scans: dict[tuple, dict] = {}
        self._scored: dict[tuple, tuple[str, Any, Any]] = {}
        self._fitting: dict[tuple, float | None] = {}

    def scan(self, cfg, scenario_name: str, settle_frames: int, divergence_factor: float,
             run: Callable[[], dict]) -> dict:
        """The best-gain integrator's scan of ``cfg`` (gains, leak, refinement, ``data.frames`` and ``data.seed``) in
        ``scenario_name``: ``run()`` the first time, a copy of its result after."""
        key = (scenario_name, tuple(cfg.gains), cfg.leak, cfg.refine_rounds, cfg.data.frames, cfg.data.seed,
               settle_frames, divergence_factor)
        if not self.enabled:
            return run()
        if key in self._scans:
            self.reused["gain_scan"] += 1
            return copy.deepcopy(self._scans[key])
        scan = run()
        self._scans[key] = copy.deepcopy(scan)
        return scan

    def scored(self, key: tuple | None, predictor: Any, name: str, run: Callable[[], Any],
               note: Callable[[str, Any], None]) -> Any:
        """Contender ``name``'s metrics on the loops ``key`` names (:func:`loop_key`): ``run()`` unless a contender
        already ran them, then a copy of its metrics, and ``note(other, metrics)`` says whose they are."""
        if not self.enabled or key is None:
            return run()
        if key in self._scored:
            other, _, metrics = self._scored[key]
            self.reused["scored"] += 1
            metrics = copy.deepcopy(metrics)
            note(other, metrics)
            return metrics
        metrics = run()
        # The predictor is held, so its id names it while the entry lives.
        self._scored[key] = (name, predictor, copy.deepcopy(metrics))
        return metrics

    def fitting(self, key: tuple, run: Callable[[], float | None]) -> float | None:
        """The fitting error of the stream ``key`` names (scenario, seed, stream, frames, settling, realisations):
        ``run()`` once."""
        if not self.enabled:
            return run()
        if key in self._fitting:
            self.reused["fitting"] += 1
        else:
            self._fitting[key] = run()
        return self._fitting[key]
