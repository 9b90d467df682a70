"""Planning a sweep (each run's seed and draws) and flying it as Ray tasks: on this machine by default,
on a cluster given its address (the same code). A worker that dies has its task run again (Ray's
``max_retries``); each result is appended to ``results.jsonl`` as it comes, so a second call with the
same plan flies only the runs not yet there, while everything that decides them is unchanged
(`hil.sweep.inputs`); a folder that holds results of anything else is flown afresh, saying why."""

from __future__ import annotations

import contextlib
import json
import logging
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from hil.scenario.dispersions import base_document, run_seeds, sample
from hil.scenario.schema import Dispersions, Scenario
from hil.sweep.fly import RunRecord, fly
from hil.sweep.inputs import changed, fingerprint, run_inputs

RESULTS_NAME = "results.jsonl"
PLAN_NAME = "plan.json"
#: times Ray runs a task again when its worker process dies (a killed worker loses no result)
TASK_RETRIES = 3


@dataclass(frozen=True)
class SweepPlan:
    """Every run of a sweep: its seed and draws, what decides their outcome by content (`run_inputs`:
    the scenario, its dispersions, the files it names, the project's files) and their fingerprint:
    results of another plan are never resumed."""

    scenario: Scenario
    dispersions: Dispersions
    seeds: tuple[int, ...]
    values: tuple[dict[str, Any], ...]
    out: Path
    inputs: dict[str, str]

    @property
    def fingerprint(self) -> str:
        return fingerprint(self.inputs)

    @property
    def runs(self) -> int:
        return len(self.seeds)


def plan_sweep(scenario: Scenario, out: str | Path, runs: int | None = None, seed: int | None = None,
               ) -> SweepPlan:
    """The plan of ``scenario``'s sweep (its ``dispersions`` block; ``runs``/``seed`` override it)."""
    d = scenario.dispersions
    if d is None:
        raise ValueError(f"{scenario.source}: {scenario.id} has no dispersions block to sweep")
    if seed is not None:
        d = replace(d, seed=seed)
    n = d.runs if runs is None else runs
    if n < 1:
        raise ValueError(f"runs must be >= 1, got {n}")
    doc = base_document(scenario)
    seeds = tuple(run_seeds(d, n))
    values = tuple(sample(d, doc, s) for s in seeds)
    return SweepPlan(scenario, d, seeds, values, Path(out), run_inputs(scenario, d))


def stale(plan: SweepPlan) -> str | None:
    """Why the results in ``plan``'s folder are not ``plan``'s (they are flown again), or None: there
    are none, or they are its own."""
    plan_file, results = plan.out / PLAN_NAME, plan.out / RESULTS_NAME
    if not results.is_file() or not results.read_text().strip():
        return None
    try:
        then = json.loads(plan_file.read_text())
    except (OSError, ValueError):
        return f"its {PLAN_NAME} is missing or unreadable"
    if not isinstance(then, dict):
        return f"its {PLAN_NAME} is not a plan"
    if then.get("fingerprint") == plan.fingerprint:
        return None
    return changed(then.get("inputs"), plan.inputs)


def finished(plan: SweepPlan) -> dict[int, RunRecord]:
    """The runs of ``plan`` already in its folder (from an earlier call with the same plan)."""
    results = plan.out / RESULTS_NAME
    if not results.is_file() or stale(plan) is not None:
        return {}
    out: dict[int, RunRecord] = {}
    for line in results.read_text().splitlines():
        try:
            rec = RunRecord.from_dict(json.loads(line))
        except (ValueError, TypeError):
            continue  # a line cut short when the last call was killed
        if rec.index < plan.runs and rec.seed == plan.seeds[rec.index]:
            out[rec.index] = rec
    return out


Progress = Callable[[RunRecord, int, int], None]


#: Ray's switch for a node that keeps to this machine: it takes 127.0.0.1 as its own address, and its
#: services (GCS, raylet, object manager, workers, agents) listen there, not on every interface. Ray
#: reads it when it is imported (here, in a process that has not imported it yet; in each of its own
#: processes, which inherit it) and at the moment a node is started (`_keep_to_loopback`).
LOOPBACK_ONLY_ENV = ("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
LOOPBACK = "127.0.0.1"


def _keep_to_loopback() -> None:
    """Make the Ray started next a node of this machine only (see `LOOPBACK_ONLY_ENV`)."""
    name, value = LOOPBACK_ONLY_ENV
    os.environ[name] = value
    # Ray is imported here, not at the top: an optional, heavy dependency (the sweep extra)
    from ray._private import ray_constants

    # a Ray imported before the variable was set read it then; the node's address is looked up at start
    ray_constants.ENABLE_RAY_CLUSTER = False


def init_local_ray(num_cpus: int) -> None:
    """Start Ray on this machine with ``num_cpus`` CPUs, every service on 127.0.0.1 and no dashboard."""
    _keep_to_loopback()
    import ray  # an optional, heavy dependency (the sweep extra)

    ray.init(num_cpus=num_cpus, include_dashboard=False, _node_ip_address=LOOPBACK,
             logging_level=logging.WARNING, log_to_driver=False)
    address = ray.get_runtime_context().gcs_address.rsplit(":", 1)[0]
    if address != LOOPBACK:  # a later Ray that ignores the switch: never serve on every interface
        ray.shutdown()
        raise RuntimeError(f"local Ray took {address} as its address, not {LOOPBACK}: it would be "
                           "reachable from other machines; start one with `ray start --head` and pass "
                           "its address instead")


@contextlib.contextmanager
def ray_session(address: str | None, jobs: int) -> Iterator[None]:
    """Ray for the duration of the block: the cluster at ``address``, else ``jobs`` CPUs on this
    machine (`init_local_ray`: reachable from this machine only); a Ray already running (started by
    the caller) is used as it is and left running."""
    import ray  # an optional, heavy dependency (the sweep extra)

    if ray.is_initialized():
        yield
        return
    if address:
        ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
    else:
        init_local_ray(jobs)
    try:
        yield
    finally:
        ray.shutdown()


def ray_imap(fn: Callable[..., Any], common: tuple[Any, ...], calls: list[tuple[Any, ...]],
             ) -> Iterator[tuple[int, Any]]:
    """``fn(*common, *calls[k])`` for every k as Ray tasks (run again, up to `TASK_RETRIES` times, when
    their worker dies), as ``(k, result)`` in the order they finish; the result is the exception when a
    task failed for good. ``common`` goes to Ray's object store once. Needs a Ray session (`ray_session`)."""
    import ray

    task = ray.remote(max_retries=TASK_RETRIES)(fn)
    refs = [ray.put(a) for a in common]
    pending = {task.remote(*refs, *args): k for k, args in enumerate(calls)}
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        k = pending.pop(ready[0])
        try:
            yield k, ray.get(ready[0])
        except ray.exceptions.RayError as exc:
            yield k, exc


def run_sweep(plan: SweepPlan, *, address: str | None = None, jobs: int = 2, in_process: bool = True,
              progress: Progress | None = None) -> list[RunRecord]:
    """Fly every run of ``plan`` not finished yet as a Ray task and return all its records.

    Ray is started here (``jobs`` CPUs on this machine, or the cluster at ``address``) unless it is
    running already; ``progress(record, done, total)`` is called as each run finishes."""
    plan.out.mkdir(parents=True, exist_ok=True)
    done = finished(plan)
    if not done:  # a new plan: its results start afresh
        (plan.out / RESULTS_NAME).write_text("")
    (plan.out / PLAN_NAME).write_text(json.dumps(
        {"fingerprint": plan.fingerprint, "scenario": plan.scenario.id, "source": plan.scenario.source,
         "runs": plan.runs, "seed": plan.dispersions.seed, "inputs": plan.inputs}, indent=2) + "\n")
    todo = [i for i in range(plan.runs) if i not in done]
    records = dict(done)
    if progress is not None:
        for k, rec in enumerate(sorted(done.values(), key=lambda r: r.index)):
            progress(rec, k + 1, plan.runs)
    if not todo:
        return [records[i] for i in range(plan.runs)]
    calls = [(i, plan.seeds[i], plan.values[i], str(plan.out.resolve()), in_process) for i in todo]
    with ray_session(address, jobs), (plan.out / RESULTS_NAME).open("a", encoding="utf-8") as sink:
        for k, rec in ray_imap(fly, (plan.scenario,), calls):
            if isinstance(rec, BaseException):  # retries spent, or the task raised
                i = todo[k]
                rec = RunRecord(i, plan.seeds[i], plan.values[i], False,
                                error=f"the run's task failed: {type(rec).__name__}: {rec}"[:2000])
            records[rec.index] = rec
            sink.write(json.dumps(rec.to_dict(), default=str) + "\n")
            sink.flush()
            if progress is not None:
                progress(rec, len(records), plan.runs)
    return [records[i] for i in range(plan.runs)]
