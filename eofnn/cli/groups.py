"""The configuration groups of the subcommands that run a scenario (they import the simulator: torch, HCIPy)."""

from dataclasses import dataclass, field
from typing import Any, ClassVar

from eofnn.cli.common import Output
from eofnn.evaluation.config import EvaluationConfig
from eofnn.sim.loop.plant import Plant
from eofnn.sim.scenario import Scenario


@dataclass(kw_only=True)
class SimulationCommand(Output):
    """A command that runs a scenario.

    Parameters
    ----------
    scenario : Scenario
        Telescope (grid), atmosphere, frame rate and plant (delay and model errors).
    progress : bool, optional
        Progress bars (default: only when stderr is a terminal).
    trusted_networks : list of str
        Network class paths, beyond eofnn's own, that checkpoints may name (importing a module runs its code: name
        only modules you trust).
    """

    scenario: Scenario = field(default_factory=Scenario)
    progress: bool | None = None
    trusted_networks: list[str] = field(default_factory=list)


@dataclass(kw_only=True)
class ExperimentCommand(SimulationCommand):
    """A command that evaluates controllers in closed loop in several scenarios (compare, evaluate).

    Parameters
    ----------
    scenarios : dict
        Scenario name -> plant changes, e.g. {nominal: {}, dm_gain_2: {dm_gain: 2.0}}; the names are the plant's
        fields: {plant_fields}.
    evaluation : EvaluationConfig
        Closed-loop evaluation settings.
    allow_long : bool
        Run an experiment estimated to take more than a day (refused otherwise).
    reference : dict, optional
        Published numbers (scenario -> controller -> median RMS nm) shown beside ours.
    """

    scenarios: dict[str, dict[str, Any]] = field(default_factory=lambda: {"nominal": {}})
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    allow_long: bool = False
    reference: dict[str, dict[str, float]] | None = None

    #: Free mappings whose values change a dataclass: each scenario's keys are fields of the plant (config files'
    #: keys are checked against them, :func:`eofnn.cli.configfile.check_config_keys`).
    _mapping_value_keys: ClassVar[dict[str, type]] = {"scenarios": Plant}


ExperimentCommand.__doc__ = ExperimentCommand.__doc__.replace("{plant_fields}", ", ".join(Plant.model_error_names()))
