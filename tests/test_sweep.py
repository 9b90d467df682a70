"""Dispersed runs (`hil dryrun`): the dispersions block validated as the rest of a scenario file, the
fields a sweep disperses acting on the flight (a mis-measured gap, a heavier airframe), and sweeps flown
as Ray tasks for real: the same seed gives the same results, a second call resumes, failures are
ranked by check and phase with their reports, and the go/no-go follows the threshold."""

from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.runner import RunOptions, run_scenario
from hil.scenario import ScenarioError, load_scenarios, loads_scenarios
from hil.scenario.dispersions import base_document, run_seeds, sample
from hil.scenario.loader import dispersed
from hil.sweep import plan_sweep, run_sweep, summarise, wilson_interval
from hil.sweep.inputs import PROJECT, VERSION, changed, project_version, tree_digest
from hil.sweep.report import rate_colour, write_sweep
from hil.sweep.sweep import init_local_ray, stale

BASE = "description: t\ngap: {roll_deg: 30}\nduration_s: 9\n"
SWEPT = BASE + """dispersions:
  runs: 8
  seed: 5
  go: {min_success: 0.5, confidence: 0.9}
  vary:
    mocap_bias.gap_pos_m[2]: {choice: [0.0, 0.3]}
    links.mocap.latency_ms: {uniform: [0, 10]}
    airframe.mass_scale: {normal: [1.0, 0.02]}
    initial.pos_m: {normal: [0, 0.03], offset: true}
    wind.speed_m_s: {uniform: [0, 2]}
"""


def error_of(text: str) -> ScenarioError:
    with pytest.raises(ScenarioError) as info:
        loads_scenarios(text, source="x.scenario.yaml")
    return info.value


@pytest.mark.parametrize(
    ("vary", "field", "words"),
    [
        ("gap.rol_deg: {uniform: [0, 1]}", "dispersions.vary.gap.rol_deg", "has no field 'rol_deg'"),
        ("gap.roll_deg: {uniform: [10, 95]}", "dispersions.vary.gap.roll_deg",
         "a draw of 95.0 makes no valid scenario: gap.roll_deg: expected a number between -90 and 90"),
        ("gap.roll_deg: {uniform: [5, 1]}", "dispersions.vary.gap.roll_deg.uniform", "low <= high"),
        ("gap.roll_deg: {uniform: [0, 1], normal: [0, 1]}", "dispersions.vary.gap.roll_deg",
         "exactly one of uniform, normal, choice"),
        ("gap.roll_deg: {normal: [0, -1]}", "dispersions.vary.gap.roll_deg.normal", "deviation >= 0"),
        ("gap.roll_deg: {gauss: [0, 1]}", "dispersions.vary.gap.roll_deg.gauss", "unknown field"),
        ("seed: {uniform: [0, 9]}", "dispersions.vary.seed", "not dispersed"),
        ("links.mocap.burst.p_gb: {uniform: [0, 1]}", "dispersions.vary.links.mocap.burst.p_gb",
         "links.mocap.burst is null in this scenario"),
        ("gap: {uniform: [0, 1]}", "dispersions.vary.gap", "is a block of fields"),
    ],
)
def test_a_bad_dispersion_names_its_line_field_and_why(vary, field, words):
    e = error_of(BASE + f"dispersions:\n  vary:\n    {vary}\n")
    assert e.field == field and words in e.message, str(e)
    assert e.line == 6, str(e)


def test_the_envelope_names_paths_that_are_dispersed():
    e = error_of(BASE + "dispersions:\n  envelope: [gap.roll_deg, x.y]\n  vary:\n    gap.roll_deg: "
                        "{uniform: [0, 10]}\n    approach.speed_m_s: {uniform: [2, 3]}\n")
    assert e.field == "dispersions.envelope[1]" and "expected a path of vary" in e.message


def test_the_envelope_is_mapped_over_numbers_not_vectors():
    e = error_of(BASE + "dispersions:\n  envelope: [gap.roll_deg, initial.pos_m]\n  vary:\n    gap.roll_deg: "
                        "{uniform: [0, 10]}\n    initial.pos_m: {normal: [0, 0.1], offset: true}\n")
    assert e.field == "dispersions.envelope" and "initial.pos_m[0]" in e.message, str(e)


def test_draws_follow_each_runs_seed_and_land_in_the_scenario():
    [s] = loads_scenarios(SWEPT)
    assert s.dispersions is not None
    seeds = run_seeds(s.dispersions, 8)
    assert seeds[:3] == run_seeds(s.dispersions, 3)  # a longer sweep extends a shorter one
    assert len(set(seeds)) == 8
    doc = base_document(s)
    v = sample(s.dispersions, doc, seeds[0])
    assert v == sample(s.dispersions, doc, seeds[0])
    assert v["mocap_bias.gap_pos_m[2]"] in (0.0, 0.3) and 0 <= v["links.mocap.latency_ms"] <= 10
    assert [abs(a - b) < 0.2 for a, b in zip(v["initial.pos_m"], s.initial.pos_m, strict=True)] == [True] * 3
    d = dispersed(s, v, seeds[0], "t-0000")
    assert d.seed == seeds[0] and d.id == "t-0000" and d.dispersions is None
    assert d.links.mocap.latency_ms == pytest.approx(v["links.mocap.latency_ms"])
    assert d.airframe.mass_scale == pytest.approx(v["airframe.mass_scale"])
    wind = [f for f in d.faults if f.kind == "wind_gust"]
    assert len(wind) == 1 and wind[0].start_s == 0.0 and wind[0].end_s is None
    assert wind[0].params.speed_m_s == pytest.approx(v["wind.speed_m_s"])  # type: ignore[union-attr]


def test_a_mis_measured_gap_is_what_the_onboard_side_flies_to(tmp_path):
    [clean] = loads_scenarios(BASE)
    [biased] = loads_scenarios(BASE + "mocap_bias: {gap_pos_m: [0, 0, 0.25]}\n")
    a = run_scenario(clean, tmp_path / "a", RunOptions(in_process=True))
    b = run_scenario(biased, tmp_path / "b", RunOptions(in_process=True))
    assert a.passed
    # the program aims at the reported centre, 0.25 m above the true one, and the true wall is hit
    assert b.summary["crossing"]["point_m"][2] == pytest.approx(a.summary["crossing"]["point_m"][2] + 0.25,
                                                                abs=0.03)
    assert [c.name for c in b.failed_checks] == ["collision"]


def test_a_heavier_airframe_needs_more_thrust_than_the_onboard_side_was_told(tmp_path):
    [clean] = loads_scenarios(BASE)
    [heavy] = loads_scenarios(BASE + "airframe: {mass_scale: 1.2}\n")
    a = run_scenario(clean, tmp_path / "a", RunOptions(in_process=True))
    b = run_scenario(heavy, tmp_path / "b", RunOptions(in_process=True))
    assert b.summary["mean_thrust_n"] / a.summary["mean_thrust_n"] == pytest.approx(1.2, abs=0.02)


def test_wilson_interval():
    assert wilson_interval(10, 10, 0.95) == pytest.approx((0.7225, 1.0), abs=1e-4)
    assert wilson_interval(0, 10, 0.95) == pytest.approx((0.0, 0.2775), abs=1e-4)
    assert wilson_interval(5, 10, 0.95) == pytest.approx((0.2366, 0.7634), abs=1e-4)


@pytest.fixture(scope="module")
def local_ray():
    ray = pytest.importorskip("ray")
    init_local_ray(2)
    yield ray
    ray.shutdown()


def _fingerprint(records):
    return [(r.index, r.seed, r.passed, r.min_clearance_m, [f["check"] for f in r.failed]) for r in records]


def test_a_sweep_on_ray_is_repeatable_resumable_and_ranks_its_failures(tmp_path, local_ray):
    path = tmp_path / "t.scenario.yaml"
    path.write_text(SWEPT)
    [s] = load_scenarios(path)
    first = run_sweep(plan_sweep(s, tmp_path / "a"))
    again = run_sweep(plan_sweep(s, tmp_path / "b"))
    assert _fingerprint(first) == _fingerprint(again)  # same seed, same results
    biased = [r for r in first if r.values["mocap_bias.gap_pos_m[2]"] > 0]
    assert biased and all(not r.passed and "collision" in [f["check"] for f in r.failed] for r in biased)
    assert all(r.passed for r in first if r not in biased)
    # a second call flies nothing: every run is read back from the first call's results
    seen: list[int] = []
    resumed = run_sweep(plan_sweep(s, tmp_path / "a"), progress=lambda rec, done, total: seen.append(done))
    assert [r.worker for r in resumed] == [r.worker for r in first] and seen == list(range(1, 9))
    # a longer sweep flies only the new runs
    more = run_sweep(plan_sweep(s, tmp_path / "a", runs=10))
    assert _fingerprint(more[:8]) == _fingerprint(first) and len(more) == 10
    result = summarise(s.id, s.dispersions, first)  # type: ignore[arg-type]
    assert result.passed == 8 - len(biased) and result.counted == 8
    rows = result.failures
    assert [f["runs"] for f in rows] == sorted((f["runs"] for f in rows), reverse=True)
    assert sum(f["runs"] for f in rows if f["check"] == "collision") == len(biased)
    assert {f["phase"] for f in rows} <= {"approach", "traverse"}
    top = rows[0]
    report = tmp_path / "a" / top["examples"][0]["report"]
    assert report.is_file()
    # a passed run keeps its summary, .tlog and time series, but no page (a sweep's runs need none)
    ok = next(r for r in first if r.passed)
    assert ok.report is None and (tmp_path / "a" / "runs" / f"{ok.index:04d}" / "run.tlog").is_file()
    assert not (tmp_path / "a" / "runs" / f"{ok.index:04d}" / "report.html").exists()
    assert result.go == (result.interval[0] >= 0.5)
    page = write_sweep(tmp_path / "a", result, s.description, 1.0).read_text()
    assert "collision" in page and top["examples"][0]["report"] in page
    assert json.loads((tmp_path / "a" / "sweep.json").read_text())["passed"] == result.passed


def _descendants(root: int) -> dict[int, str]:
    """The process ``root`` and its descendants, by pid, with their names (from /proc)."""
    parent, names = {}, {}
    for d in Path("/proc").iterdir():
        with contextlib.suppress(OSError, ValueError, IndexError):
            stat = (d / "stat").read_text()
            parent[int(d.name)] = int(stat.rsplit(")", 1)[1].split()[1])
            names[int(d.name)] = stat[stat.index("(") + 1:stat.rindex(")")]
    tree, grew = {root}, True
    while grew:
        more = {pid for pid, pp in parent.items() if pp in tree} - tree
        tree |= more
        grew = bool(more)
    return {pid: names[pid] for pid in tree if pid in names}


def _address(hex_ip: str) -> str:
    raw = bytes.fromhex(hex_ip)  # /proc/net/*: 32-bit words in the host's (little-endian) order
    return str(ipaddress.ip_address(b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))))


def _listening(root: int) -> dict[str, set[str]]:
    """The addresses ``root`` and its descendants listen on (TCP) or are bound to (UDP, unconnected), by
    process name: the sockets of /proc/net/{tcp,tcp6,udp,udp6} whose inode one of them holds."""
    procs = _descendants(root)
    owner = {}
    for pid in procs:
        with contextlib.suppress(OSError):
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                with contextlib.suppress(OSError):
                    link = os.readlink(fd)
                    if link.startswith("socket:["):
                        owner[int(link[8:-1])] = procs[pid]
    out: dict[str, set[str]] = {}
    for table, listen in (("tcp", "0A"), ("tcp6", "0A"), ("udp", "07"), ("udp6", "07")):
        for row in Path(f"/proc/net/{table}").read_text().splitlines()[1:]:
            f = row.split()
            if f[3] == listen and int(f[9]) in owner and int(f[2].split(":")[0], 16) == 0:
                out.setdefault(owner[int(f[9])], set()).add(_address(f[1].split(":")[0]))
    return out


def _loopback(ip: str) -> bool:
    a = ipaddress.ip_address(ip)
    return (a.ipv4_mapped or a).is_loopback if isinstance(a, ipaddress.IPv6Address) else a.is_loopback


def test_hil_dryrun_exits_by_go_or_no_go_and_its_ray_listens_on_loopback_only(tmp_path):
    path = tmp_path / "t.scenario.yaml"
    path.write_text(SWEPT.replace("runs: 8", "runs: 4").replace("min_success: 0.5", "min_success: 0.99"))
    p = subprocess.Popen([sys.executable, "-m", "hil.cli", "dryrun", str(path), "--out", str(tmp_path / "o"),
                          "-j", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    seen: dict[str, set[str]] = {}
    deadline = time.monotonic() + 300
    while p.poll() is None and time.monotonic() < deadline:  # every socket Ray's processes listen on
        for name, ips in _listening(p.pid).items():
            seen.setdefault(name, set()).update(ips)
        time.sleep(0.1)
    stdout, stderr = p.communicate(timeout=max(deadline - time.monotonic(), 1))
    assert {"gcs_server", "raylet"} <= set(seen), seen  # watched while Ray ran
    assert all(_loopback(ip) for ips in seen.values() for ip in ips), seen
    assert p.returncode == 1, stdout + stderr  # 4 runs can never show 0.99 with 90 % confidence
    assert "NO-GO" in stdout and "4/4 runs" in stdout
    assert (tmp_path / "o" / "sweep.html").is_file()
    bad = tmp_path / "bad.scenario.yaml"
    bad.write_text(BASE)
    q = subprocess.run([sys.executable, "-m", "hil.cli", "dryrun", str(bad)], capture_output=True, text=True,
                       timeout=60, cwd=tmp_path)
    assert q.returncode == 2 and "dispersions" in q.stderr


def test_a_worker_killed_mid_sweep_loses_no_result(tmp_path, local_ray):
    import os
    import signal

    path = tmp_path / "t.scenario.yaml"
    path.write_text(SWEPT)
    [s] = load_scenarios(path)
    killed: list[int] = []

    def kill_first_worker(rec, done, total):  # the worker that flew the first run is flying another now
        if not killed:
            pid = int(rec.worker.rsplit(":", 1)[1])
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    records = run_sweep(plan_sweep(s, tmp_path / "k"), progress=kill_first_worker)
    assert killed and len(records) == 8
    assert sum(r.worker.endswith(f":{killed[0]}") for r in records) == 1  # its later runs flown elsewhere
    assert [r.index for r in records] == list(range(8))
    assert all(r.error is None for r in records), [r.error for r in records]
    lines = (tmp_path / "k" / "results.jsonl").read_text().splitlines()
    assert sorted(json.loads(x)["index"] for x in lines) == list(range(8))
    # the same answers as a sweep no worker died in
    clean = run_sweep(plan_sweep(s, tmp_path / "c"))
    assert _fingerprint(records) == _fingerprint(clean)


def test_hil_suite_flies_on_ray_given_an_address(tmp_path, local_ray, capsys):
    from hil.cli import main

    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "a.scenario.yaml").write_text(BASE)
    (tmp_path / "s" / "b.scenario.yaml").write_text(BASE + "mocap_bias: {gap_pos_m: [0, 0, 0.25]}\n")
    code = main(["suite", str(tmp_path / "s"), "--in-process", "--ray-address", "auto", "--out",
                 str(tmp_path / "o")])
    out = capsys.readouterr().out
    assert code == 1 and "PASSED a" in out and "FAILED b" in out and "1/2 passed" in out
    index = json.loads((tmp_path / "o" / "index.json").read_text())
    assert {r["id"]: r["passed"] for r in index["results"]} == {"a": True, "b": False}


def _own_vehicle(folder):
    """The built-in vehicle as a profile file of the user's, with its onboard configuration beside it."""
    from importlib import resources

    profile = folder / "quad.yaml"
    profile.write_text((resources.files("emulator") / "profiles" / "n3_tx2.yaml").read_text())
    (folder / "quad.onboard.yaml").write_text(
        (resources.files("policies") / "vehicles" / "n3_tx2.yaml").read_text())
    return profile


def test_a_resumed_sweep_flies_again_what_a_changed_vehicle_file_decides(tmp_path, local_ray):
    profile = _own_vehicle(tmp_path)
    path = tmp_path / "t.scenario.yaml"
    path.write_text(SWEPT.replace("runs: 8", "runs: 2") + "vehicle: quad.yaml\n")
    [s] = load_scenarios(path)
    first = run_sweep(plan_sweep(s, tmp_path / "a"))
    assert stale(plan_sweep(s, tmp_path / "a")) is None
    # the airframe is heavier now: the same scenario text, another vehicle
    profile.write_text(profile.read_text().replace("mass_kg: 0.9", "mass_kg: 1.2"))
    [s] = load_scenarios(path)
    plan = plan_sweep(s, tmp_path / "a")
    assert stale(plan) == f"the vehicle profile {profile} changed"
    resumed = run_sweep(plan)
    fresh = run_sweep(plan_sweep(s, tmp_path / "b"))
    assert _fingerprint(resumed) == _fingerprint(fresh) != _fingerprint(first)
    assert stale(plan_sweep(s, tmp_path / "a")) is None  # and it resumes those from now on


def test_a_sweep_is_stale_when_the_onboard_configuration_the_project_or_an_old_plan_file_differ(tmp_path):
    _own_vehicle(tmp_path)
    path = tmp_path / "t.scenario.yaml"
    path.write_text(SWEPT + "vehicle: quad.yaml\n")
    [s] = load_scenarios(path)
    plan = plan_sweep(s, tmp_path)
    (tmp_path / "results.jsonl").write_text('{"index": 0}\n')
    (tmp_path / "plan.json").write_text(json.dumps({"fingerprint": plan.fingerprint, "inputs": plan.inputs}))
    assert stale(plan) is None
    onboard = tmp_path / "quad.onboard.yaml"
    onboard.write_text(onboard.read_text().replace("max_tilt_deg: 75.0", "max_tilt_deg: 70.0"))
    assert stale(plan_sweep(s, tmp_path)) == f"the onboard configuration {onboard} changed"
    other = dict(plan.inputs, **{PROJECT: "0" * 16, VERSION: "0.0.9"})
    assert changed(other, plan.inputs) == f"{PROJECT}, {VERSION} (0.0.9 -> {project_version()}) changed"
    (tmp_path / "plan.json").write_text(json.dumps({"fingerprint": "abc"}))  # a plan file of an old version
    assert "did not record what decided them" in str(stale(plan))
    (tmp_path / "plan.json").write_text("{cut sh")
    assert "unreadable" in str(stale(plan))


def test_the_project_digest_follows_every_file_of_the_packages(tmp_path):
    (tmp_path / "p" / "weights").mkdir(parents=True)
    (tmp_path / "p" / "m.py").write_text("x = 1\n")
    (tmp_path / "p" / "weights" / "w.onnx").write_bytes(b"\0\1")
    before = tree_digest({"p": tmp_path / "p"})
    (tmp_path / "p" / "weights" / "w.onnx").write_bytes(b"\0\2")
    assert tree_digest({"p": tmp_path / "p"}) != before
    (tmp_path / "p" / "weights" / "w.onnx").write_bytes(b"\0\1")
    assert tree_digest({"p": tmp_path / "p"}) == before
    (tmp_path / "p" / "__pycache__").mkdir()
    (tmp_path / "p" / "__pycache__" / "m.cpython-311.pyc").write_bytes(b"compiled")
    assert tree_digest({"p": tmp_path / "p"}) == before  # a compiled cache is not a change


def test_the_sweep_page_names_every_varied_field_colours_by_the_go_line_and_says_why_runs_aborted(tmp_path):
    from hil.sweep.fly import RunRecord
    from hil.sweep.report import render

    [s] = loads_scenarios(BASE + """dispersions:
  go: {min_success: 0.8}
  bins: 2
  vary:
    initial.pos_m: {normal: [0, 0.03], offset: true}
    pilot: {choice: [traditional, e2e]}
""")
    abort = {"check": "onboard_abort", "phase": "approach", "time_s": 2.6, "expected": "no abort",
             "observed": "aborted: planning_failed (the opening is too small)"}
    # x below 0.5: 9 of 10 pass (above the 0.8 line); x above: 7 of 10 (just under it)
    records = [RunRecord(i, i, {"initial.pos_m": [0.25 if i < 10 else 0.75, 1.0, 2.0 + i / 100],
                                "pilot": "e2e" if i % 2 else "traditional"},
                         passed=not (i == 0 or i >= 17), failed=() if not (i == 0 or i >= 17) else (abort,))
               for i in range(20)]
    result = summarise(s.id, s.dispersions, records)  # type: ignore[arg-type]
    page = render(result, s.description, 1.0)
    for name in ("initial.pos_m[0]", "initial.pos_m[1]", "initial.pos_m[2]", "pilot", "e2e", "traditional"):
        assert name in page, name
    assert "planning_failed (the opening is too small)" in page
    bins = result.by_field["initial.pos_m[0]"]
    assert [(b["passed"], b["runs"]) for b in bins] == [(9, 10), (7, 10)]
    above, below = rate_colour(0.9, 0.8), rate_colour(0.7, 0.8)
    assert above != below and f"background:{above}" in page and f"background:{below}" in page
    assert rate_colour(0.0, 0.8) != below  # red far under the line, amber just under it
    assert "go threshold (80 %)" in page
