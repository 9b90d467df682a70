"""The pytest plugin (pytest11 entry point `crossgap_hil`): every ``*.scenario.yaml`` is collected as a
file of tests, one item per document; a bad file is a collection error naming the file, line and field.

    pytest scenarios/ -n 2                  # the whole suite, two workers
    pytest scenarios/ --pilot e2e           # the same suite flown by another pilot
    pytest scenarios/ --hil-out reports/    # where each run's report goes (default: pytest's tmp dir)
    pytest scenarios/ --hil-vehicle f450    # the same suite flown by another vehicle profile

A failed scenario shows its failed checks (expected, observed, sim time) and the report's path.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hil.link.protocols import PROTOCOLS
from hil.scenario import ScenarioError, loads_scenarios
from hil.scenario.loader import SUFFIX
from hil.scenario.schema import Scenario

# The emulator and the runner (numba kernels, the onboard program) are imported inside the hooks that
# need them, not here: this plugin is loaded in every pytest session of an environment that installs it.


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("crossgap-hil", "scenario files (*.scenario.yaml)")
    group.addoption("--pilot", default=None, help="fly every scenario with this pilot")
    group.addoption("--hil-out", default=None, metavar="DIR", help="write each scenario's report under DIR")
    group.addoption(
        "--hil-in-process",
        action="store_true",
        default=False,
        help="run both sides in the test process over memory links (default: ptys)",
    )
    group.addoption(
        "--hil-cold-start",
        action="store_true",
        default=False,
        help="start the onboard program as a new interpreter each run (default: forked warm)",
    )
    group.addoption("--hil-backend", default=None, help="physics backend for every scenario")
    group.addoption(
        "--hil-realtime",
        action="store_true",
        default=False,
        help="fly every scenario on the wall clock (a pilot's dry run) instead of in lockstep",
    )
    group.addoption(
        "--hil-protocol",
        default=None,
        choices=PROTOCOLS.keys(),
        help="the command link's protocol for every scenario (default: each scenario's, mavlink)",
    )
    group.addoption(
        "--hil-vehicle",
        default=None,
        metavar="NAME|PATH",
        help="vehicle profile for every scenario (an opening narrower than its body grows)",
    )


#: markers the shipped scenarios use (any other marker in a file works too, with pytest's warning)
SCENARIO_MARKERS = {
    "tilt": "scenario: gap tilt sweep",
    "speed": "scenario: approach speed",
    "position": "scenario: gap/start position",
    "links": "scenario: link quality",
    "faults": "scenario: injected faults",
    "lab": "scenario: lab bounds",
    "negative": "scenario: the pipeline must fail and the harness must say so",
    "jsbsim": "scenario: JSBSim backend",
    "quality": "scenario: a flight-quality check must catch a badly flown run",
}


def pytest_configure(config: pytest.Config) -> None:
    for name, text in SCENARIO_MARKERS.items():
        config.addinivalue_line("markers", f"{name}: {text}")
    pilot = config.getoption("--pilot", None)
    if pilot is not None:  # as a vehicle: an unknown pilot is a usage error, not a failure per scenario
        from policies.onboard.pilots import pilot_names  # (the onboard side only when a pilot is given)

        if pilot not in pilot_names():
            raise pytest.UsageError(f"--pilot {pilot}: unknown pilot; one of {', '.join(pilot_names())}")
    vehicle = config.getoption("--hil-vehicle", None)
    if vehicle is not None:  # a vehicle that does not load is a usage error, not a failure per scenario
        from emulator.profile import load_profile  # (the emulator only when a vehicle is given)

        try:
            load_profile(vehicle)
        except ValueError as exc:
            raise pytest.UsageError(f"--hil-vehicle {vehicle}: {exc}") from exc


def _xdist_workers() -> tuple[int, int]:
    """This pytest-xdist worker's number and how many there are ((0, 1) without xdist)."""
    name = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    count = os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")
    number = name[2:] if name.startswith("gw") else "0"
    return (int(number) if number.isdigit() else 0), (int(count) if count.isdigit() else 1)


def pytest_collection_finish(session: pytest.Session) -> None:
    """Start the onboard program's fork server while pytest gets ready, when scenarios will fly over ptys
    warm (the default)."""
    cfg = session.config
    if cfg.getoption("--hil-in-process") or cfg.getoption("--hil-cold-start"):
        return
    if any(isinstance(item, ScenarioItem) for item in session.items):
        from hil.runner.onboard_side import prestart  # (the runner only when scenarios were collected)

        prestart()


def pytest_collect_file(parent: pytest.Collector, file_path: Path) -> ScenarioFile | None:
    if file_path.name.endswith(SUFFIX):
        return ScenarioFile.from_parent(parent, path=file_path)
    return None


class ScenarioFileError(Exception):
    """A scenario file that does not load (shown as a collection error)."""


class ScenarioFile(pytest.File):
    """One ``*.scenario.yaml``: one test item per document."""

    def collect(self) -> Iterator[ScenarioItem]:
        try:
            scenarios = loads_scenarios(self.path.read_text(encoding="utf-8"), source=str(self.path))
        except ScenarioError as exc:
            raise ScenarioFileError(str(exc)) from None
        vehicle = self.config.getoption("--hil-vehicle")
        if vehicle:
            from hil.runner.run import not_applicable  # (the runner only when a vehicle is given)
        for s in scenarios:
            item = ScenarioItem.from_parent(self, name=s.id, scenario=s)
            for marker in s.markers:
                item.add_marker(marker)
            if s.skip:
                item.add_marker(pytest.mark.skip(reason=s.skip))
            elif vehicle and (why := not_applicable(s, vehicle)):
                item.add_marker(pytest.mark.skip(reason=f"not applicable to {vehicle}: {why}"))
            yield item

    def repr_failure(self, excinfo: pytest.ExceptionInfo[BaseException], style: Any = None) -> str:
        if isinstance(excinfo.value, ScenarioFileError):
            return f"bad scenario file: {excinfo.value}"
        return super().repr_failure(excinfo)


class ScenarioFailed(Exception):
    """A scenario ran and some of its checks failed."""

    def __init__(self, scenario: Scenario, failed: list[Any], report: Path) -> None:
        super().__init__(scenario.id)
        self.scenario, self.failed, self.report = scenario, failed, report


class ScenarioItem(pytest.Item):
    """One scenario document, flown by the runner."""

    def __init__(self, *, scenario: Scenario, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.scenario = scenario

    def runtest(self) -> None:
        from hil.runner import RunOptions, run_scenario  # (the runner only when a scenario runs)

        cfg = self.config
        out_root = cfg.getoption("--hil-out")
        if out_root:
            out = Path(out_root) / self.scenario.id
        else:
            factory = cfg._tmp_path_factory  # type: ignore[attr-defined]
            out = factory.mktemp(self.scenario.id, numbered=True)
        options = RunOptions(
            pilot=cfg.getoption("--pilot"),
            in_process=True if cfg.getoption("--hil-in-process") else None,
            backend=cfg.getoption("--hil-backend"),
            realtime=True if cfg.getoption("--hil-realtime") else None,
            vehicle=cfg.getoption("--hil-vehicle"),
            protocol=cfg.getoption("--hil-protocol"),
            cold_start=cfg.getoption("--hil-cold-start"),
            # pytest-xdist's workers, each flying one run at a time
            worker=_xdist_workers()[0],
            parallel_runs=_xdist_workers()[1],
        )
        result = run_scenario(self.scenario, out, options)
        self.user_properties.append(("report", str(result.report_path)))
        self.user_properties.append(("sim_time_s", result.summary.get("sim_time_s")))
        if not result.passed:
            raise ScenarioFailed(self.scenario, list(result.failed_checks), result.report_path)

    def repr_failure(self, excinfo: pytest.ExceptionInfo[BaseException], style: Any = None) -> str:
        exc = excinfo.value
        if isinstance(exc, ScenarioFailed):
            lines = [f"scenario {exc.scenario.id} ({exc.scenario.source}:{exc.scenario.line}) failed:"]
            for c in exc.failed:
                when = "whole run" if c.time_s is None else f"t = {c.time_s:.3f} s"
                lines.append(f"  {c.name}: expected {c.expected}; observed {c.observed} ({when})")
            lines.append(f"  report: {exc.report}")
            return "\n".join(lines)
        return super().repr_failure(excinfo)

    def reportinfo(self) -> tuple[Path, int, str]:
        return self.path, self.scenario.line - 1, f"scenario: {self.scenario.id}"
