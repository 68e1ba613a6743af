"""``compare``'s stages around the experiment's run, as functions: what the command line calls, in order.

A compare is: plan it (:func:`plan_compare`: its analyses, :func:`plan_analyses`, every name and grid checked, and
its experiment set up, every refusal made, before anything runs), run the experiment
(:meth:`~eofnn.evaluation.experiment.Experiment.run`: tune, train, guard and evaluate every controller in every
scenario), then analyse it (:func:`analyse`): the DM-gain intervals of the controllers without a linear model, found
by closed-loop simulation (the verdict recomputed to quote them); the robustness map over a grid of plants; the Pareto
front of the linear families along their tuning paths (:func:`run_compare` runs the last two). Writing it all is the
reporting floor's (:func:`eofnn.reporting.experiment.write_experiment`). ``eofnn sweep`` plans each of its points
with the same :func:`plan_compare` and runs each as a compare.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from eofnn.errors import ConfigError

#: Controllers with no loop to analyse: no DM-gain interval is simulated for them.
NO_LOOP = ("uncorrected", "pseudo_integrator")


@dataclass(frozen=True)
class AnalysisPlan:
    """The analyses after the run, checked.

    Parameters
    ----------
    simulated_margins : tuple of str
        Scenarios in which the DM-gain interval of every controller without a linear model is simulated.
    grid : dict
        The robustness map's plant field(s) -> values (:func:`eofnn.evaluation.robustness.check_grid`); empty: none.
    pareto_scenario : str or None
        The scenario of the Pareto front; None: none.
    """

    simulated_margins: tuple[str, ...] = ()
    grid: dict[str, list[float]] = field(default_factory=dict)
    pareto_scenario: str | None = None


def plan_analyses(scenarios: Sequence[str], *, robustness: Mapping[str, list[float]] | None = None,
                  simulated_margins: Sequence[str] = (), pareto: bool | str = False) -> AnalysisPlan:
    """Check the analyses a compare asks for against its ``scenarios`` (names, in order) and resolve them:
    ``pareto: true`` is the first scenario. A bad grid or an unknown scenario is one line naming it."""
    from eofnn.evaluation.robustness import check_grid

    grid = check_grid(robustness)
    simulated_margins = tuple(simulated_margins)
    if pareto is True:
        pareto = next(iter(scenarios))
    for scenario_name in simulated_margins + ((pareto,) if pareto else ()):
        if scenario_name not in scenarios:
            raise ConfigError(f"simulated_margins or pareto: {scenario_name!r} is not a scenario: allowed are "
                              f"{', '.join(scenarios)}")
    return AnalysisPlan(simulated_margins, grid, pareto or None)


@dataclass
class ComparePlan:
    """A compare, checked before anything runs: its experiment set up and its analyses planned."""

    experiment: object  # eofnn.evaluation.experiment.Experiment
    analyses: AnalysisPlan


def plan_compare(scenario, scenarios: Mapping[str, dict], predictors: Mapping[str, object], evaluation, *,
                 robustness: Mapping[str, list[float]] | None = None, simulated_margins: Sequence[str] = (),
                 pareto: bool | str = False, progress: bool | None = None, log: Callable[[str], None] = print,
                 trusted_networks: Sequence[str] = (), allow_long: bool = False) -> ComparePlan:
    """Everything a compare can refuse, before anything runs: its analyses (:func:`plan_analyses`), then its
    experiment (:class:`~eofnn.evaluation.experiment.Experiment`: the scenarios, the contenders, their checkpoints,
    the memory and the time), each refusal one line. The arguments are :class:`~eofnn.cli.compare.CompareConfig`'s."""
    from eofnn.evaluation.experiment import Experiment

    analyses = plan_analyses(list(scenarios or ()), robustness=robustness, simulated_margins=simulated_margins,
                             pareto=pareto)
    experiment = Experiment(scenario, scenarios, predictors, evaluation, progress=progress, log=log,
                            trusted_networks=trusted_networks, allow_long=allow_long)
    return ComparePlan(experiment, analyses)


@dataclass
class Analyses:
    """What :func:`analyse` computed beyond the experiment's own result (which it completes in place)."""

    robustness: object | None = None  # eofnn.evaluation.robustness.RobustnessResult
    pareto: object | None = None  # eofnn.evaluation.pareto.ParetoResult


def add_simulated_margins(experiment, result, scenario_names: Sequence[str],
                          log: Callable[[str], None] = print) -> None:
    """Simulate the DM-gain interval of every controller of ``experiment`` with no analytic one in each of
    ``scenario_names`` (:func:`eofnn.evaluation.margins.simulated_dm_gain_interval`) into
    ``result.simulated_stability``, and recompute ``result.verdict`` so that it quotes them."""
    from eofnn.evaluation.margins import simulated_dm_gain_interval

    for scenario_name in scenario_names:
        for name in experiment.predictors:
            if name not in result.stability.get(scenario_name, {}) and name not in NO_LOOP:
                log(f"{scenario_name:>12s} {name:>18s}: DM-gain interval by simulation ...")
                result.simulated_stability.setdefault(scenario_name, {})[name] = simulated_dm_gain_interval(
                    experiment, name, scenario_name)
    if scenario_names:  # the verdict quotes the intervals found by simulation too
        result.verdict = experiment.verdict(result)


def analyse(experiment, result, plan: AnalysisPlan, log: Callable[[str], None] = print) -> Analyses:
    """The analyses of ``plan`` after ``experiment`` ran into ``result``, in order: the simulated margins (into
    ``result``), the robustness map, the Pareto front."""
    from eofnn.evaluation.pareto import pareto
    from eofnn.evaluation.robustness import robustness_map

    add_simulated_margins(experiment, result, plan.simulated_margins, log)
    return Analyses(robustness_map(experiment, plan.grid) if plan.grid else None,
                    pareto(experiment, plan.pareto_scenario) if plan.pareto_scenario is not None else None)


def run_compare(plan: ComparePlan, log: Callable[[str], None] = print):
    """Run ``plan``'s experiment, then its analyses (:func:`analyse`): ``(result, analyses)``."""
    result = plan.experiment.run()
    return result, analyse(plan.experiment, result, plan.analyses, log)
