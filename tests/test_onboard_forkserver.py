"""Warm starts of the onboard program (`policies.onboard.forkserver`): each run a fresh fork of a
pre-imported server, watched, signalled and reaped as a cold process is; the same runs, byte for byte,
as cold starts; faults on the process as cold."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.runner import RunOptions, run_scenario
from hil.runner.onboard_side import program_env
from hil.scenario import load_scenarios, loads_scenarios
from policies.onboard import forkserver

pytestmark = pytest.mark.skipif(not forkserver.available(), reason="warm starts need Linux 5.3+ (pidfds)")
SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"

SHORT = """
description: a short level crossing, long enough to take off and fly part of the approach
gap: {roll_deg: 30}
approach: {speed_m_s: 2.0}
duration_s: 5
"""


@pytest.fixture()
def server():
    s = forkserver.ForkServer(program_env())
    yield s
    s.close()


def test_two_warm_runs_give_the_same_tlog_bytes_as_two_cold_starts(tmp_path):
    s = loads_scenarios(SHORT)[0]
    runs = {
        (start, k): run_scenario(s, tmp_path / f"{start}{k}", RunOptions(cold_start=start == "cold"))
        for start in ("warm", "cold")
        for k in range(2)
    }
    assert all(r.summary["mode"]["onboard_start"] == start for (start, _), r in runs.items())
    tlogs = {key: r.tlog_path.read_bytes() for key, r in runs.items()}
    assert len(tlogs[("warm", 0)]) > 10_000  # a flight, not an empty log
    assert len(set(tlogs.values())) == 1, {k: len(v) for k, v in tlogs.items()}
    # the program's own events and counters too: nothing carried over from the run before
    events = {key: [(e["text"], e["time_s"]) for e in r.summary["events"] if e["source"] == "onboard"]
              for key, r in runs.items()}
    assert events[("warm", 1)] == events[("cold", 0)]
    # its counters too, but the command link's: the first tick is sent again every 2 ms (wall) until the
    # program has opened its port, and how many copies it reads after it did depends on scheduling
    counters = {key: {k: v for k, v in r.summary["onboard"].items() if k != "mavlink"}
                for key, r in runs.items()}
    assert counters[("warm", 1)] == counters[("cold", 0)] == counters[("warm", 0)]


def test_a_run_reports_the_cpu_time_of_each_side(tmp_path):
    """The summary's ``cpu_s``: the harness's process and, forked warm, the onboard program's (from its
    exit status, as its fork server reaped it); unknown for a cold start or one sharing the process."""
    s = loads_scenarios(SHORT)[0]
    options = {"warm": RunOptions(), "cold": RunOptions(cold_start=True),
               "shared": RunOptions(in_process=True)}
    warm, cold, shared = (run_scenario(s, tmp_path / k, o) for k, o in options.items())
    cpu = warm.summary["cpu_s"]
    assert cpu["harness"] > 0.0
    # 500 ticks of the program's work, in a process that lived no longer than the run (one thread works)
    assert 0.01 < cpu["onboard"] < warm.summary["wall_time_s"] + 0.5
    assert cold.summary["cpu_s"]["onboard"] is None and cold.summary["cpu_s"]["harness"] > 0.0
    assert shared.summary["cpu_s"]["onboard"] is None and shared.summary["cpu_s"]["harness"] > 0.0


@pytest.mark.parametrize("name", ["onboard_killed_approach", "onboard_stalled"])
def test_a_killed_or_stalled_warm_program_behaves_as_a_cold_one(tmp_path, name):
    s = load_scenarios(SCENARIOS / f"{name}.scenario.yaml")[0]
    warm = run_scenario(s, tmp_path / "warm", RunOptions())
    cold = run_scenario(s, tmp_path / "cold", RunOptions(cold_start=True))
    assert warm.summary["mode"]["onboard_start"] == "warm"
    assert warm.passed and cold.passed
    for key in ("onboard_exit_code", "failsafe_events", "fc_final_state", "crossed_gap"):
        assert warm.summary[key] == cold.summary[key], key
    runner = [[e["text"] for e in r.summary["events"] if e["source"] == "runner"] for r in (warm, cold)]
    assert runner[0] == runner[1]
    if name == "onboard_killed_approach":
        assert warm.summary["onboard_exit_code"] == -signal.SIGKILL
        assert warm.summary["onboard"] is None  # a killed program writes no summary, warm or cold
    else:
        assert any("stalled" in t for t in runner[0]) and any("resumed" in t for t in runner[0])
    assert warm.tlog_path.read_bytes() == cold.tlog_path.read_bytes()


def test_a_forked_program_reports_its_exit_code_and_bad_options_as_a_cold_one(server, tmp_path):
    with open(tmp_path / "err", "wb") as err:
        proc = server.spawn(["--command-link", "memory", "--mocap-link", "memory", "--rate-hz", "10"], err)
        assert proc.wait(10) == 2  # refused below the N3's 50 Hz, as `python -m policies.onboard` exits
        assert proc.cpu_s is not None and 0.0 < proc.cpu_s < 5.0  # its CPU time, from its exit status
    assert "50" in (tmp_path / "err").read_text()
    cold = subprocess.run(
        [sys.executable, "-m", "policies.onboard", "--command-link", "memory", "--mocap-link", "memory",
         "--rate-hz", "10"], capture_output=True, env=program_env(),
    )
    assert cold.returncode == 2


@pytest.mark.parametrize(("cpu", "kept"), [(0.25, 0.25), (0, 0.0), (float("nan"), None), (-1.0, None),
                                         (float("inf"), None), ("0.3", None), (True, None), (None, None)])
def test_the_cpu_time_beside_an_exit_code_is_kept_only_when_it_is_a_time(cpu, kept):
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    proc = forkserver.ForkedProcess(0, os.open(os.devnull, os.O_RDONLY), ours)
    theirs.send(json.dumps({"exit": 0, "cpu_s": cpu}).encode())
    assert proc.poll() == 0  # the exit code stands whatever came beside it
    assert proc.cpu_s == kept
    theirs.close()


def test_a_forked_program_is_stopped_continued_and_killed_through_its_pidfd(server, tmp_path):
    # a program waiting for an FC that never speaks: it runs until it is ended
    from hil.link.pty import PtyTransport

    with PtyTransport.create() as cmd, PtyTransport.create() as moc, open(tmp_path / "err", "wb") as err:
        proc = server.spawn([f"--command-link=serial:{cmd.endpoint}:921600",
                             f"--mocap-link=serial:{moc.endpoint}:921600", "--quiet"], err)
        assert proc.poll() is None
        proc.send_signal(signal.SIGSTOP)
        assert _state_within(proc.pid, ("T",))  # stopped
        proc.send_signal(signal.SIGCONT)
        assert _state_within(proc.pid, ("S", "R"))
        proc.kill()
        assert proc.wait(5) == -signal.SIGKILL
        proc.kill()  # a process already reaped: nothing happens (its pid may be someone else's now)


def test_a_forked_program_keeps_to_the_cpus_of_the_harness_that_asked_for_it(server, tmp_path):
    from hil.link.pty import PtyTransport
    from hil.runner.lockstep import kept_to

    cpu = max(os.sched_getaffinity(0))
    with PtyTransport.create() as cmd, PtyTransport.create() as moc, open(tmp_path / "err", "wb") as err:
        with kept_to(cpu):
            proc = server.spawn([f"--command-link=serial:{cmd.endpoint}:921600",
                                 f"--mocap-link=serial:{moc.endpoint}:921600", "--quiet"], err)
        deadline = time.monotonic() + 5
        while os.sched_getaffinity(proc.pid) != {cpu} and time.monotonic() < deadline:
            time.sleep(0.01)  # (it keeps to them as it starts)
        assert os.sched_getaffinity(proc.pid) == {cpu}
        assert os.sched_getaffinity(server.proc.pid) != {cpu} or len(os.sched_getaffinity(0)) == 1
        proc.kill()
        proc.wait(5)


def test_a_forked_program_ended_by_sigterm_exits_143_with_its_summary(server, tmp_path):
    from hil.link.pty import PtyTransport

    log = tmp_path / "events.jsonl"
    with PtyTransport.create() as cmd, PtyTransport.create() as moc, open(tmp_path / "err", "wb") as err:
        proc = server.spawn([f"--command-link=serial:{cmd.endpoint}:921600",
                             f"--mocap-link=serial:{moc.endpoint}:921600", "--quiet", "--log-json", str(log)],
                            err)
        deadline = time.monotonic() + 10
        while (not log.exists() or '"start"' not in log.read_text()) and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)  # (its SIGTERM handler goes in right after the start event)
        proc.terminate()
        assert proc.wait(10) == 143
    assert '"summary"' in log.read_text()


def test_a_server_that_has_gone_is_an_error_and_the_run_starts_cold(tmp_path, monkeypatch):
    dead = forkserver.ForkServer(program_env())
    dead.proc.kill()
    dead.proc.wait()
    with open(tmp_path / "err", "wb") as err, pytest.raises(forkserver.ForkServerError):
        dead.spawn(["--help"], err)
    dead.close()
    monkeypatch.setattr(forkserver, "shared", lambda env=None: dead)
    r = run_scenario(loads_scenarios(SHORT)[0], tmp_path / "run", RunOptions())
    assert r.summary["mode"]["onboard_start"] == "cold"
    assert "started cold" in (tmp_path / "run" / "onboard_stderr.txt").read_text()
    assert r.summary["ticks_answered"] == r.summary["ticks"]


def _state_within(pid: int, states: tuple[str, ...], timeout_s: float = 10.0) -> bool:
    """Whether process ``pid`` is in one of ``states`` within ``timeout_s`` (a signal's effect shows once
    the host schedules it: at once on a quiet one, later on a busy one)."""
    end = time.monotonic() + timeout_s
    while _state(pid) not in states and time.monotonic() < end:
        time.sleep(0.01)
    return _state(pid) in states


def _state(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


FAILING_TEST = """
import signal, subprocess, sys
from hil.link.pty import PtyTransport
from hil.runner.onboard_side import program_env
from policies.onboard import forkserver

def test_that_fails_and_leaves_stopped_processes(tmp_path):
    server = forkserver.ForkServer(program_env())
    cmd, moc = PtyTransport.create(), PtyTransport.create()
    err = open(tmp_path / "err", "wb")
    proc = server.spawn([f"--command-link=serial:{cmd.endpoint}:921600",
                         f"--mocap-link=serial:{moc.endpoint}:921600", "--quiet"], err)
    proc.send_signal(signal.SIGSTOP)
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    sleeper.send_signal(signal.SIGSTOP)
    print("PIDS", proc.pid, sleeper.pid)
    assert False, "a test that fails before its clean-up"
"""


@pytest.mark.parametrize("plugin", [True, False], ids=["with_the_tests_plugin", "fork_server_alone"])
def test_a_failing_tests_processes_are_ended_stopped_ones_included(tmp_path, plugin):
    """A test that fails with a forked program and a subprocess both stopped (SIGSTOP): once its pytest
    has ended, the fork server has ended its child (continued, then killed), and the tests' plugin
    (tests/processes.py) everything else; nothing of that pytest session is left."""
    from processes import kill_session, processes_of_session

    (tmp_path / "test_leaves.py").write_text(FAILING_TEST)
    tests = Path(__file__).resolve().parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tests), str(tests.parent)])}
    args = [sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider", "-n", "0",
            *(["-p", "processes"] if plugin else []), str(tmp_path / "test_leaves.py")]
    log = tmp_path / "pytest.out"  # (a file: a stopped process left holding a pipe would keep it open)
    with log.open("w") as f:
        p = subprocess.Popen(args, cwd=tmp_path, env=env, stdout=f, stderr=subprocess.STDOUT,
                             start_new_session=True)
    try:
        p.wait(timeout=120)
        out = log.read_text()
        assert p.returncode == 1 and "a test that fails before its clean-up" in out, out
        forked, sleeper = (int(x) for x in out.split("PIDS ", 1)[1].split()[:2])
        end = time.monotonic() + 10.0
        while time.monotonic() < end and (_alive(forked) or (plugin and processes_of_session(p.pid))):
            time.sleep(0.1)
        assert not _alive(forked), _state(forked)
        if plugin:
            assert processes_of_session(p.pid) == [] and "ending 3 processes the tests left" in out, out
        else:
            assert _alive(sleeper)  # (a plain subprocess: only the plugin ends it)
    finally:
        kill_session(p.pid)


def _alive(pid: int) -> bool:
    try:
        return _state(pid) != "Z"
    except OSError:
        return False
