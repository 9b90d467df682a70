"""The live view in a real browser (headless Chromium over the DevTools protocol): during a real-time
run the page loads, the vehicle moves between frames that come at least 20 times a second, and a
command-link fault shows the failsafe banner; when the run ends the same page replays it with a time
slider, as `hil view RUN_DIR` does. `hil fc --view` streams the standalone FC the same way."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest
from browser import Browser

HIL = [sys.executable, "-m", "hil.cli"]
# the approach starts about 3.9 s in; the command link goes down in it and the FC fails safe 1 s later
SCENARIO = """
description: the command link is lost in the approach; the FC fails safe to a hover
gap: {roll_deg: 30}
faults:
  - {kind: command_link_down, start_s: 4.8}
duration_s: 8
expect: {crosses_gap: false, recovery: false, failsafe_expected: hover}
"""
BANNER = "document.getElementById('banner')"


def _url(proc: subprocess.Popen[str]) -> str:
    """The URL the command prints first; the rest of its output is read on (by a thread) so that a full
    pipe never blocks it, which would keep it from ending when told to."""
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.startswith("view: http://127.0.0.1:"), line
    threading.Thread(target=proc.stdout.read, daemon=True).start()
    return line.split()[1]


def _default_ctrl_c() -> None:
    """In the child before it runs: Ctrl-C as at a terminal. A test run started in the background by a
    shell inherits SIGINT ignored, and so would the command, which then could not be stopped by it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _stop(proc: subprocess.Popen[str]) -> int:
    proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(20)
    finally:
        if proc.poll() is None:
            proc.kill()


def _check_replay(b: Browser) -> None:
    """The replayed run: a slider over its frames; the vehicle moves and the banner follows the time."""
    n = b.wait_for("hilView.mode === 'replay' && hilView.frames.length")
    assert n > 200  # 8 s and more at 50 frames a second
    assert b.eval("document.getElementById('slider').max") == str(n - 1)
    assert "FAILSAFE" in b.eval(f"{BANNER}.textContent")  # the last frame: failsafe hover
    b.eval("setIndex(10)")
    assert b.eval("hilView.index") == 10
    assert b.wait_for(f"{BANNER}.style.display === 'none'")
    early = b.eval("hilView.frames[10].pos")
    b.eval(f"setIndex({n // 2 + 40})")
    assert b.eval("hilView.frames[hilView.index].pos") != early


@pytest.mark.realtime
def test_the_live_page_follows_a_realtime_run_then_replays_it(tmp_path):
    path = tmp_path / "live.scenario.yaml"
    path.write_text(SCENARIO)
    b = Browser(tmp_path / "profile")  # started first: a browser takes seconds to start on a busy host
    stderr = tmp_path / "stderr.txt"  # a file: a busy host's lateness warnings would fill a pipe
    proc = subprocess.Popen([*HIL, "run", str(path), "--realtime", "--in-process", "--view", "--out",
                             str(tmp_path / "run")],
                            stdout=subprocess.PIPE, stderr=stderr.open("w"), text=True,
                            preexec_fn=_default_ctrl_c)
    try:
        url = _url(proc)
        b.open(url)
        assert b.wait_for("hilView.mode === 'live' && hilView.received > 0", 30)
        assert b.eval("document.getElementById('title').textContent") == "live (live)"
        # frames at least 20 times a second
        n0, w0 = b.eval("hilView.received"), time.monotonic()
        time.sleep(2.0)
        rate = (b.eval("hilView.received") - n0) / (time.monotonic() - w0)
        assert rate >= 20, rate
        # the vehicle moves between two frames of the approach, and the page draws it
        b.wait_for("hilView.frames.length && hilView.frames[hilView.index].t > 4.4", 30)
        a = b.eval("hilView.frames[hilView.index]")
        # no banner before the failsafe (checked at once: on a busy host the screenshots take a while)
        assert b.eval(f"{BANNER}.style.display") == "none" or b.eval("hilView.frames[hilView.index].t") > 5.8
        b.screenshot(tmp_path / "a.png")
        b.wait_for(f"hilView.frames[hilView.index].t > {a['t'] + 0.6}", 10)
        c = b.eval("hilView.frames[hilView.index]")
        b.screenshot(tmp_path / "b.png")
        moved = sum((p - q) ** 2 for p, q in zip(a["pos"], c["pos"], strict=True)) ** 0.5
        assert moved > 0.1, (a, c)
        assert (tmp_path / "a.png").read_bytes() != (tmp_path / "b.png").read_bytes()
        assert b.eval("hilView.scene.plan_m && hilView.scene.plan_m.length") > 10  # the plan is drawn
        assert not any(b.eval("hilView.frames.filter(f => f.t < 5.5).map(f => f.banner)"))
        # the command link goes down: the FC fails safe and the banner says so
        text = b.wait_for(f"{BANNER}.style.display === 'block' && {BANNER}.textContent", 20)
        assert "FC FAILSAFE: failsafe_hover" in text
        assert b.eval("document.getElementById('panel').textContent").count("command_link_down") == 1
        # the run ends: the same page replays it
        _check_replay(b)
        b.screenshot(tmp_path / "replay.png")
    finally:
        b.close()
        code = _stop(proc)
    # the exit code is the run's verdict, the view's Ctrl-C notwithstanding (on a busy host a real-time
    # run may fail its `realtime` check: the view does not decide that)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert code == (0 if summary["passed"] else 1), stderr.read_text()
    assert {c["name"] for c in summary["checks"] if not c["passed"]} <= {"realtime"}
    # and `hil view` replays the folder the same way
    view = subprocess.Popen([*HIL, "view", str(tmp_path / "run")], stdout=subprocess.PIPE,
                            stderr=(tmp_path / "view_stderr.txt").open("w"), text=True,
                            preexec_fn=_default_ctrl_c)
    b = Browser(tmp_path / "profile2")
    try:
        b.open(_url(view))
        _check_replay(b)
    finally:
        b.close()
        assert _stop(view) == 0


def test_hil_view_refuses_a_folder_without_a_run(tmp_path):
    p = subprocess.run([*HIL, "view", str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "holds no finished run" in p.stderr


def test_hil_fc_view_streams_the_standalone_fc(tmp_path):
    proc = subprocess.Popen([*HIL, "fc", "--view", "--duration", "30", "--mocap-link", "none"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        endpoints = json.loads(proc.stdout.readline())
        url = endpoints["view"]
        assert url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(url + "state.json", timeout=10) as r:
            state = json.load(r)
        assert state["mode"] == "live" and state["scene"]["gap"]["width_m"] > 0
        ts = []
        for _ in range(2):
            time.sleep(0.5)
            with urllib.request.urlopen(url + "frame.json", timeout=10) as r:
                frame = json.load(r)
            ts.append(frame["t"])
            assert frame["fc"] == "disarmed" and frame["banner"] is None
        assert ts[1] > ts[0]  # the FC's clock goes on in the frames
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0


@pytest.fixture(autouse=True)
def _quiet_cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the runs write reports/ where they are started
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).resolve().parents[1]))


def test_a_run_folder_as_mcap_for_foxglove(tmp_path):
    import math

    from mcap.reader import make_reader

    from hil.link.mavlink import euler_from_quat, quat_enu_flu_to_ned_frd
    from hil.report.timeseries import read_timeseries

    path = tmp_path / "m.scenario.yaml"
    path.write_text("description: m\ngap: {roll_deg: 45}\nduration_s: 9\n")
    p = subprocess.run([*HIL, "run", str(path), "--in-process", "--mcap", "--out", str(tmp_path / "r")],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "mcap:" in p.stdout, p.stdout + p.stderr
    cols = read_timeseries(tmp_path / "r")
    with (tmp_path / "r" / "run.mcap").open("rb") as f:
        msgs = [(ch.topic, json.loads(m.data)) for _, ch, m in make_reader(f).iter_messages()]
    poses = [d for topic, d in msgs if topic == "/vehicle/pose"]
    assert len(poses) == len(cols["t_s"])
    assert len([1 for topic, _ in msgs if topic == "/state"]) == len(poses)
    assert any("offboard" in d["message"] for topic, d in msgs if topic == "/events")
    # the pose's orientation (body FLU -> world ENU) is the recorded attitude, the steepest one too
    i = int(cols["roll_deg"].__abs__().argmax())
    o = poses[i]["pose"]["orientation"]
    q = quat_enu_flu_to_ned_frd([o["w"], o["x"], o["y"], o["z"]])
    rpy = [math.degrees(a) for a in euler_from_quat(q)]
    assert abs(cols["roll_deg"][i]) > 30
    assert rpy == pytest.approx([cols["roll_deg"][i], cols["pitch_deg"][i], cols["yaw_deg"][i]], abs=1e-6)
    assert poses[i]["pose"]["position"]["x"] == pytest.approx(cols["pos_m_x"][i])
    # hil view --mcap writes the same from a folder
    (tmp_path / "r" / "run.mcap").unlink()
    p = subprocess.run([*HIL, "view", str(tmp_path / "r"), "--mcap"], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 0 and (tmp_path / "r" / "run.mcap").stat().st_size > 10_000


def test_the_view_answers_malformed_requests_and_keeps_serving():
    """Garbage, unsupported methods, an over-long path, too many headers, a path out of the page's
    folder and a client that connects and says nothing: each gets an error (or nothing), and the page
    and its state are still served."""
    import socket

    from hil.view.server import ViewServer

    view = ViewServer()
    host, port = view._httpd.server_address[:2]
    cases = {
        b"\x00\xff garbage\r\n\r\n": b"400",
        b"POST / HTTP/1.1\r\nHost: x\r\nContent-Length: 5\r\n\r\nhello": b"501",
        b"GET /" + b"a" * 70000 + b" HTTP/1.1\r\n\r\n": b"414",
        b"GET / HTTP/1.1\r\n" + b"X: y\r\n" * 200 + b"\r\n": b"431",
        b"GET / HTTP/9.9\r\n\r\n": b"505",
        b"DELETE /stream HTTP/1.1\r\n\r\n": b"501",
        b"GET /../../etc/passwd HTTP/1.1\r\n\r\n": b"404",
    }
    idle = socket.create_connection((host, port))  # connects and says nothing
    try:
        for request, code in cases.items():
            with socket.create_connection((host, port), timeout=5) as s:
                s.sendall(request)
                s.shutdown(socket.SHUT_WR)
                answer = b""
                while chunk := s.recv(65536):
                    answer += chunk
            assert code in answer[:2000], (request[:40], answer[:200])
        with urllib.request.urlopen(f"http://{host}:{port}/state.json", timeout=5) as r:
            assert r.status == 200 and isinstance(json.loads(r.read()), dict)
        with urllib.request.urlopen(f"http://{host}:{port}/", timeout=5) as r:
            assert b"<html" in r.read(2000).lower()
    finally:
        idle.close()
        view.close()


TWO_SCENARIOS = """
name: first
description: a short hover before the approach
gap: {roll_deg: 30}
duration_s: 2
expect: {crosses_gap: false, recovery: false}
---
name: second
description: the same, again
gap: {roll_deg: 30}
duration_s: 2
expect: {crosses_gap: false, recovery: false}
"""


@pytest.mark.realtime
def test_the_page_follows_each_scenario_of_a_file_live_in_turn(tmp_path):
    path = tmp_path / "two.scenario.yaml"
    path.write_text(TWO_SCENARIOS)
    b = Browser(tmp_path / "profile")
    proc = subprocess.Popen([*HIL, "run", str(path), "--realtime", "--in-process", "--view", "--out",
                             str(tmp_path / "runs")],
                            stdout=subprocess.PIPE, stderr=(tmp_path / "stderr.txt").open("w"), text=True,
                            preexec_fn=_default_ctrl_c)
    try:
        b.open(_url(proc))
        assert b.wait_for("hilView.mode === 'live' && hilView.received > 0", 30)
        assert b.eval("document.getElementById('title').textContent") == "first (live)"
        # the first ends, the second starts: the same page follows it live, then replays it
        assert b.wait_for("hilView.mode === 'live' && hilView.scene.title === 'second (live)' "
                          "&& hilView.frames.length > 0", 60)
        assert b.eval("hilView.frames[0].t") < 1.0  # its own frames, from its start
        assert b.wait_for("hilView.mode === 'replay' && hilView.frames.length", 60) > 50
        assert b.eval("hilView.runs") == 2
    finally:
        b.close()
        _stop(proc)
    assert {p.name for p in (tmp_path / "runs").iterdir()} == {"first", "second"}


class _Scripted:
    """A view source that says which run it is in each frame."""

    def __init__(self, name: str) -> None:
        self.name = name

    def scene(self) -> dict:
        return {"title": self.name}

    def frame(self) -> dict:
        return {"t": 0.0, "run": self.name}


def test_a_runs_stream_ends_when_it_ends_even_if_the_next_starts_at_once():
    """The runner finishes one scenario and starts the next within microseconds: a page's stream of the
    first ends with `done` and never carries the second's frames (under load it used to go on with
    them, so the page showed the next run inside the last one's)."""
    from hil.view.server import ViewServer

    view = ViewServer(rate_hz=200.0)
    host, port = view._httpd.server_address[:2]
    try:
        for _ in range(5):
            view.live(_Scripted("first"))
            got: list[bytes] = []
            reader = threading.Thread(target=lambda out=got: out.append(
                urllib.request.urlopen(f"http://{host}:{port}/stream", timeout=10).read()))
            reader.start()
            time.sleep(0.1)  # frames of the first run on the stream
            view.finish(None)
            view.live(_Scripted("second"))  # at once, in the same thread, as the runner does
            reader.join(timeout=10)
            assert not reader.is_alive(), "the stream did not end with its run"
            body = got[0].decode()
            assert '"run":"first"' in body and '"run":"second"' not in body
            assert body.rstrip().endswith("event: done\ndata: {}")
            view.finish(None)
    finally:
        view.close()


# an earlier run in the same folder: another gap, and an abort the live run has none of
EARLIER = """
description: an earlier run, its gap elsewhere; its onboard program aborts when the mocap goes
gap: {roll_deg: -30, centre_m: [0.3, 0.8, 1.6]}
faults:
  - {kind: mocap_dropped, start_s: 4.0, end_s: 8.0}
duration_s: 6
expect: {crosses_gap: false, recovery: false, onboard_abort_expected: true}
"""
# the command link goes down in the approach: the run fails its crossing and recovery checks
FAILING = SCENARIO.replace("expect: {crosses_gap: false, recovery: false, failsafe_expected: hover}",
                           "expect: {failsafe_expected: hover}")


@pytest.mark.realtime
def test_a_page_opened_late_or_reloaded_shows_this_runs_whole_log_and_why_it_failed(tmp_path):
    from hil.view.live import plan_points

    earlier, failing, out = tmp_path / "earlier.scenario.yaml", tmp_path / "f.scenario.yaml", tmp_path / "run"
    earlier.write_text(EARLIER)
    failing.write_text(FAILING)
    p = subprocess.run([*HIL, "run", str(earlier), "--in-process", "--out", str(out)], capture_output=True,
                       text=True, timeout=300)
    old_events = [json.loads(x) for x in (out / "onboard_events.jsonl").read_text().splitlines()]
    old_plan = plan_points(old_events)
    assert old_plan and any(e["event"] == "abort" for e in old_events), p.stdout + p.stderr
    b = Browser(tmp_path / "profile")
    proc = subprocess.Popen([*HIL, "run", str(failing), "--realtime", "--in-process", "--view", "--out",
                             str(out)], stdout=subprocess.PIPE, stderr=(tmp_path / "stderr.txt").open("w"),
                            text=True, preexec_fn=_default_ctrl_c)
    try:
        url = _url(proc)
        # the page is opened 5 s into the run: it shows the run from its start all the same
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            with urllib.request.urlopen(url + "frame.json", timeout=10) as r:
                frame = json.load(r)
            if frame and frame["t"] > 5.0:
                break
            time.sleep(0.2)
        b.open(url)
        assert b.wait_for("hilView.mode === 'live' && hilView.frames.length && "
                          "hilView.frames[hilView.index].t > 5.0", 30)
        first = b.eval("hilView.frames[0]")
        assert first["t"] < 0.2 and first["k"] == 0
        log = b.eval("document.getElementById('log').textContent")
        assert "onboard start" in log and "onboard segment: approach" in log, log
        assert "abort" not in log  # the earlier run's abort is not this run's
        assert b.wait_for("hilView.scene.plan_m && hilView.scene.plan_m.length", 20)
        live_plan = b.eval("hilView.scene.plan_m")
        assert live_plan != old_plan
        # reloaded: the whole log again, from the start
        b.open(url)
        assert b.wait_for("hilView.mode === 'live' && hilView.frames.length > 100 && "
                          "hilView.frames[0].t < 0.2", 30)
        # the run ends: the page says which checks failed, and when
        text = b.wait_for("hilView.mode === 'replay' && document.getElementById('checks').textContent", 60)
        assert "FAILED crosses_gap" in text and "FAILED recovery" in text, text
        assert b.eval("hilView.scene.plan_m") == live_plan
    finally:
        b.close()
        _stop(proc)
    events = [json.loads(x) for x in (out / "onboard_events.jsonl").read_text().splitlines()]
    assert plan_points(events) == live_plan and not any(e["event"] == "abort" for e in events)
    # `hil view` says it too
    view = subprocess.Popen([*HIL, "view", str(out)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, preexec_fn=_default_ctrl_c)
    try:
        assert view.stdout is not None and view.stdout.readline().startswith("view: http://127.0.0.1:")
        lines = [view.stdout.readline() for _ in range(3)]
        assert lines[0].strip() == "FAILED", lines
        assert any(x.startswith("  failed crosses_gap:") for x in lines), lines
    finally:
        _stop(view)


def test_a_replay_stops_the_vehicle_where_it_hit_names_the_phases_and_the_failed_checks(tmp_path):
    from hil.runner import RunOptions, run_scenario
    from hil.scenario import loads_scenarios
    from hil.view.replay import load_replay

    # the onboard side aims 0.25 m above the true centre: the body hits the wall's top edge
    [s] = loads_scenarios("description: t\ngap: {roll_deg: 30}\nduration_s: 9\n"
                          "mocap_bias: {gap_pos_m: [0, 0, 0.25]}\n")
    r = run_scenario(s, tmp_path / "hit", RunOptions(in_process=True, html_report=False))
    hit_s = r.summary["collision_time_s"]
    data = load_replay(tmp_path / "hit")
    assert data["verdict"] == "FAILED" and data["failed_checks"][0]["name"] == "collision"
    assert data["failed_checks"][0]["time_s"] == pytest.approx(hit_s)
    after = [f for f in data["frames"] if f["t"] >= hit_s + 0.02]
    assert len(after) > 10 and all(f["pos"] == after[0]["pos"] and f["rpy"] == after[0]["rpy"] for f in after)
    phases = [f["phase"] for f in data["frames"]]
    assert phases[0] == "takeoff" and "approach" in phases and "traverse" in phases
    assert phases.index("approach") < phases.index("traverse")
    # a run refused before take-off replays as such
    [small] = loads_scenarios("description: t\ngap: {width_m: 0.2, height_m: 0.1}\n")
    run_scenario(small, tmp_path / "small", RunOptions(in_process=True))
    refused = load_replay(tmp_path / "small")
    assert refused["verdict"] == "REFUSED" and refused["frames"] == []
    assert "0.20 x 0.10 m opening is too small" in refused["refused"]


def test_the_live_rows_of_a_velocity_target_leave_attitude_and_thrust_uncommanded():
    # DJI's motion control (OSDK's moveByPositionOffset, velocity commands) gives the FC a target with no
    # attitude or thrust in it: the live view's row (and a recorded sample's) says so instead of failing
    import math

    import numpy as np

    from emulator.fc.n3 import AttitudeThrustTarget, MotionTarget
    from emulator.physics.state import VehicleState
    from emulator.profile import load_profile
    from hil.runner.recorder import state_values

    profile = load_profile("n3_tx2")
    x = VehicleState().to_vector()
    motion = MotionTarget(1.0, 0.0, 0.5, horizontal_position=False, vertical_position=False,
                          body_frame=False, yaw_rad=math.radians(30.0), yaw_rate_rad_s=None)
    row = state_values(2.0, x, motion, profile)
    assert math.isnan(row["roll_cmd_deg"]) and math.isnan(row["pitch_cmd_deg"])
    assert math.isnan(row["thrust_cmd_pct"]) and row["yaw_cmd_deg"] == pytest.approx(30.0)
    attitude = AttitudeThrustTarget(math.radians(10.0), 0.0, 0.0, None, profile.n3_full_thrust_n / 2)
    row = state_values(2.0, x, attitude, profile)
    assert row["roll_cmd_deg"] == pytest.approx(10.0) and row["thrust_cmd_pct"] == pytest.approx(50.0)
    assert np.isfinite(row["pos_m_x"])
