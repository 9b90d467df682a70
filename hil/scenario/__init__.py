"""Scenario files (`*.scenario.yaml`): the typed `Scenario` values and their line-aware loader."""

from hil.scenario.loader import ScenarioError, find_scenario_files, load_all, load_scenarios, loads_scenarios
from hil.scenario.schema import Expectations, Fault, Scenario

__all__ = [
    "Expectations",
    "Fault",
    "Scenario",
    "ScenarioError",
    "find_scenario_files",
    "load_all",
    "load_scenarios",
    "loads_scenarios",
]
