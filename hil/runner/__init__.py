"""The runner: one scenario flown with the emulator and the onboard program joined over links
(in-process or separate processes over ptys; lockstep or real time), faults injected, expectations
checked and results written."""

from hil.runner.checks import Check
from hil.runner.run import RunOptions, RunResult, RunSetupError, run_scenario

__all__ = ["Check", "RunOptions", "RunResult", "RunSetupError", "run_scenario"]
