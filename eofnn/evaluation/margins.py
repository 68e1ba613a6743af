"""Stability margins of controllers that have no linear model (networks), measured by closed-loop simulation.

The DM-gain interval of a linear controller is analytic (:mod:`eofnn.analysis.stability`); a network's is found
the way a careful user would: close the loop with the DM applying ``g`` times the command, on a stream of its own
(``"margin"``, never the test stream), and call ``g`` unstable when the run diverges or is diverging
(:class:`~eofnn.evaluation.metrics.GrowthMonitor`). Each bound is bracketed by doubling (halving) out of the
nominal gain and then bisected until the bracket is narrower than ``tolerance`` (relative to the nominal gain).
"""

from __future__ import annotations

from eofnn.evaluation.experiment import Experiment
from eofnn.evaluation.metrics import GrowthMonitor

#: Probes beyond which a bound is reported as "beyond the range searched".
HIGHEST_GAIN, LOWEST_GAIN = 8.0, 1.0 / 16


def simulated_dm_gain_interval(experiment: Experiment, name: str, scenario_name: str,
                               tolerance: float = 0.05) -> dict:
    """``{"dm_gain_interval": [low, high], "bracket": [[a, b], [c, d]], "probes": {gain: stable}}``: the DM gains
    (relative to the scenario's) between which controller ``name``, as made for ``scenario_name``, stays stable,
    each bound bracketed within ``tolerance``. ``low`` is 0 when even :data:`LOWEST_GAIN` is stable, ``high`` is
    ``None`` when even :data:`HIGHEST_GAIN` is."""
    scenario = experiment.scenarios[scenario_name]
    ev = experiment.evaluation
    nominal = scenario.plant.dm_gain
    probes: dict[float, bool] = {}

    def stable(relative: float) -> bool:
        if relative not in probes:
            plant = scenario.plant.with_errors(dm_gain=relative * nominal)
            growth = GrowthMonitor(scenario.frame_rate_hz, ev.settle_frames)
            rms = scenario.median_residual_nm(experiment.controller(name, scenario_name), ev.frames, ev.seed, "margin",
                                              ev.settle_frames, realisations=ev.realisations, plant=plant,
                                              divergence_factor=ev.divergence_factor, on_chunk=growth)
            judged = None if rms is None else growth.result()
            probes[relative] = rms is not None and not (judged is not None and judged["diverging"])
        return probes[relative]

    if not stable(1.0):
        return {"dm_gain_interval": None, "bracket": None, "probes": _probes(probes), "tolerance": tolerance}
    upper_ok, upper_bad = _bound(stable, 2.0, tolerance, HIGHEST_GAIN)  # double out of 1, then bisect
    lower_ok, lower_bad = _bound(stable, 0.5, tolerance, LOWEST_GAIN)  # halve out of 1, then bisect
    upper, lower = (upper_ok, upper_bad), (lower_bad, lower_ok)
    interval = [0.0 if lower[0] is None else (lower[0] + lower[1]) / 2,
                None if upper[1] is None else (upper[0] + upper[1]) / 2]
    return {"dm_gain_interval": interval, "bracket": [list(lower), list(upper)], "probes": _probes(probes),
            "tolerance": tolerance}


def _bound(stable, factor: float, tolerance: float, limit: float) -> tuple[float, float | None]:
    """``(last stable, first unstable)`` DM gains stepping out of 1 by ``factor`` (beyond ``limit``: ``None``
    unstable found), then bisected until they are ``tolerance`` apart."""
    ok, bad = 1.0, factor
    while stable(bad):
        ok, bad = bad, bad * factor
        if (bad > limit) if factor > 1 else (bad < limit):
            return ok, None
    while abs(bad - ok) > tolerance:
        middle = (ok + bad) / 2
        ok, bad = (middle, bad) if stable(middle) else (ok, middle)
    return ok, bad


def _probes(probes: dict[float, bool]) -> dict[str, bool]:
    return {f"{g:.4g}": ok for g, ok in sorted(probes.items())}
