"""What a process that flies many runs loads once, before them: numba's compiled kernels (from the
cache, or compiled into it first), so that no run pays for them.

A short in-process flight loads the kernels every run uses (the FC's, the physics', the world's). On a
cold cache (after an install, or any change to the emulator's sources) it compiles them instead, about
7 s on this 2-core machine, and a run with an ESC bus would compile the bus's after it, about 9 s more,
alone at the end of a suite while the other workers wait. `compile_beside` compiles such families of
kernels in child processes while the caller flies its own warm-up, on the cores that would otherwise be
idle; each child writes its kernels to the cache, where the runs find them.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess

from emulator.kernel_cache import cold
from hil.runner.run import RunOptions, RunSetupError, run_scenario
from hil.scenario import loads_scenarios
from hil.scenario.schema import Scenario

#: a short flight that loads what every run loads on its first use
WARM_UP_SCENARIO = "description: warm-up, not part of any suite\nduration_s: 0.3\n"


@dataclass(frozen=True)
class Family:
    """Kernels that only some runs use: the module they live in, a short flight that compiles them, and
    which scenarios use them."""

    module: str
    flight: str
    used_by: Callable[[Scenario], bool]


#: the families, by name
FAMILIES = {
    "esc_bus": Family("emulator.esc.kernels", WARM_UP_SCENARIO + "links:\n  esc_bus: {}\n",
                      lambda s: s.links.esc_bus is not None),
}

#: the longest a run waits for its family's kernels (s): a compile takes 10-30 s on a busy host
WAIT_TIMEOUT_S = 300.0


def warm_up(options: RunOptions, scenario_text: str = WARM_UP_SCENARIO) -> None:
    """Load here, once, what each run loads on its first use in a process (numba's compiled kernels,
    from its cache, for the options' physics and vehicle): a short in-process flight, its files thrown
    away. Nothing of it is seen by a run but the time it saves."""
    flight = RunOptions(in_process=True, backend=options.backend, vehicle=options.vehicle)
    with contextlib.suppress(RunSetupError, ValueError), tempfile.TemporaryDirectory() as tmp:
        run_scenario(loads_scenarios(scenario_text)[0], tmp, flight)


def families_of(scenarios: Iterable[Scenario]) -> list[str]:
    """The kernel families beyond every run's that ``scenarios`` use."""
    scenarios = list(scenarios)
    return [name for name, f in FAMILIES.items() if any(f.used_by(s) for s in scenarios)]


class Compiling:
    """The kernel families being compiled in child processes (see `compile_beside`). A process forked
    after them (a suite's worker) can wait for a family before a run that uses it, rather than compile
    it a second time beside the child: each child holds a pipe's write end open while it compiles, and
    its read end shows the end of the file once the child has ended, however it ended."""

    def __init__(self) -> None:
        self.procs: list[BaseProcess] = []
        self._ends: dict[str, Connection] = {}  # family -> the read end of its child's pipe

    def start(self, name: str, options: RunOptions) -> None:
        """Fork a child that compiles family ``name`` into the cache with a short flight."""
        read_end, write_end = multiprocessing.Pipe(duplex=False)
        proc = multiprocessing.get_context("fork").Process(
            target=_compile, args=(options, FAMILIES[name].flight, write_end), name=f"compile {name}",
            daemon=True)
        proc.start()
        write_end.close()  # (the child's copy alone holds the pipe open now)
        self.procs.append(proc)
        self._ends[name] = read_end

    def wait_for(self, scenario: Scenario, timeout_s: float = WAIT_TIMEOUT_S) -> None:
        """Wait until the families ``scenario`` uses are compiled (their children ended), at most
        ``timeout_s`` each; at once when none of them is being compiled."""
        for name in families_of([scenario]):
            end = self._ends.get(name)
            if end is not None:
                end.poll(timeout_s)

    def join(self) -> None:
        """Wait for the children (they end with their flight)."""
        for proc in self.procs:
            proc.join()


def _compile(options: RunOptions, scenario_text: str, write_end: Connection) -> None:
    try:
        warm_up(options, scenario_text)
    finally:
        write_end.close()


def compile_beside(families: Iterable[str], options: RunOptions) -> Compiling:
    """Start one child process (forked) for each of ``families`` not in the kernel cache yet, which
    compiles it into the cache with a short flight; none when they are cached (or the cache is the
    user's own ``NUMBA_CACHE_DIR``, or the platform does not fork). The caller joins them."""
    compiling = Compiling()
    if "fork" not in multiprocessing.get_all_start_methods():
        return compiling
    for name in families:
        if cold(FAMILIES[name].module) is not None:
            compiling.start(name, options)
    return compiling
