"""Learned pilots through the onboard registry: `planner_net` flies the network's approach with the
expert, `e2e` matches the expert on its planner's reference (also for a yawed plan and a heavier
vehicle), both hand over to the traditional pipeline after the approach and refuse bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from hil.link.mavlink import euler_from_quat
from hil.runner import RunOptions, run_scenario
from hil.scenario import loads_scenarios
from policies.controller import ExpertController
from policies.frames import rot_z
from policies.gap_planning import POINT_BODY, GapPose, LabVolume, plan_mission
from policies.learning.learned_pilots import approach_planner_inputs
from policies.learning.onnx_runtime import load_shipped, shipped_path
from policies.onboard.pilots import (
    EXPERT,
    SEGMENTS,
    FloatObservation,
    Observation,
    PilotContext,
    make_pilot,
    pilot_names,
)

LAB = LabVolume((-4.0, -3.0, 0.0), (4.0, 4.0, 4.0))
TIMES = np.linspace(0.0, 2.55, 12)


def _plan(yaw_deg: float = 0.0, start=(-2.0, -1.0, 0.5)):
    gap = GapPose.from_euler((0.0, 0.5, 2.1), math.radians(-60.0), 0.0, math.radians(yaw_deg),
                             width_m=0.8, height_m=0.35)
    return gap, plan_mission(start, gap, LAB, approach_duration_s=2.6, body=POINT_BODY)  # the paper's case


def _obs(gap, plan, t: float) -> Observation:
    ref, off = plan.reference(t), np.array([0.05, -0.04, 0.03])
    return Observation(t, ref.pos_m + off, ref.vel_m_s - 0.5 * off, ref.acc_m_s2,
                       np.array([0.05, -0.02, plan.yaw_rad]), gap, plan)


def _body_z(c) -> np.ndarray:
    cr, sr = math.cos(c.roll_rad), math.sin(c.roll_rad)
    cp, sp = math.cos(c.pitch_rad), math.sin(c.pitch_rad)
    z = np.array([cr * sp, -sr, cr * cp])  # Ry(pitch) Rx(roll) e_z, then the yaw
    return rot_z(c.yaw_rad) @ z


def _angle_deg(a, b) -> float:
    return math.degrees(math.acos(min(1.0, float(_body_z(a) @ _body_z(b)))))


def test_planner_net_tracks_the_networks_approach_with_the_expert():
    assert {"planner_net", "e2e", "traditional"} <= set(pilot_names())
    card = json.loads((shipped_path("planner").parent / "metrics.json").read_text())
    shipped = card["planner"]["paper_case"]
    gap, plan = _plan()
    pilot, expert = make_pilot("planner_net"), ExpertController(0.9)
    for t in TIMES:
        p, v, a = pilot.reference(plan, float(t))
        ref = plan.reference(float(t))
        assert np.linalg.norm(p - ref.pos_m) <= shipped["max_pos_m"] + 1e-6
        assert np.linalg.norm(v - ref.vel_m_s) <= shipped["max_vel_m_s"] + 1e-6
        assert np.linalg.norm(a - ref.acc_m_s2) <= shipped["max_acc_m_s2"] + 1e-6
        obs = _obs(gap, plan, float(t))
        assert pilot.command(obs) == expert.command(p, v, a, plan.yaw_rad, obs.pos_m, obs.vel_m_s)
    obs = _obs(gap, plan, plan.t_traverse_start_s + 0.05)  # after the approach: the traditional pipeline
    assert pilot.command(obs) == make_pilot("traditional").command(obs)


@pytest.mark.parametrize(("yaw_deg", "start", "mass_kg"), [(0.0, (-2.0, -1.0, 0.5), 0.9),
                                                          (90.0, (1.0, -2.0, 0.5), 1.8)])
def test_e2e_matches_the_expert_on_its_planner_reference(yaw_deg, start, mass_kg):
    gap, plan = _plan(yaw_deg, start)
    assert plan.yaw_rad == pytest.approx(math.radians(yaw_deg))
    pilot, expert = make_pilot("e2e", PilotContext(mass_kg=mass_kg)), ExpertController(mass_kg)
    planner, turn = load_shipped("planner"), rot_z(plan.yaw_rad)
    for t in TIMES:
        obs = _obs(gap, plan, float(t))
        x, p0 = approach_planner_inputs(plan, float(t), plan.yaw_rad)  # the frame the networks work in
        y = planner.predict(x)
        p, v, a = p0 + turn @ y[0:3], turn @ y[3:6], turn @ y[6:9]
        want, got = expert.command(p, v, a, plan.yaw_rad, obs.pos_m, obs.vel_m_s), pilot.command(obs)
        assert got.yaw_rad == pytest.approx(plan.yaw_rad)
        assert _angle_deg(got, want) < 3.0
        assert got.thrust_n == pytest.approx(want.thrust_n, abs=0.6 * mass_kg / 0.9)
    obs = _obs(gap, plan, plan.t_traverse_start_s + 0.05)
    assert pilot.command(obs) == make_pilot("traditional", PilotContext(mass_kg=mass_kg)).command(obs)


def test_learned_pilots_refuse_bad_input_and_options(tmp_path):
    gap, plan = _plan()
    obs = _obs(gap, plan, 1.0)
    bad = Observation(1.0, np.array([np.nan, 0.0, 1.0]), obs.vel_m_s, obs.acc_m_s2, obs.euler_rad, gap, plan)
    for name in ("planner_net", "e2e"):
        with pytest.raises(ValueError):
            make_pilot(name).command(bad)
        with pytest.raises(ValueError, match="unknown pilot option"):
            make_pilot(name, PilotContext(options=(("weights", "x"),)))
    with pytest.raises(ValueError, match="acc_input"):
        make_pilot("e2e", PilotContext(options=(("acc_input", "maybe"),)))
    with pytest.raises(FileNotFoundError):
        make_pilot("e2e", PilotContext(options=(("onnx", str(tmp_path / "none.onnx")),)))
    custom = make_pilot("planner_net", PilotContext(options=(("onnx", str(shipped_path("planner"))),)))
    assert custom.command(obs) == make_pilot("planner_net").command(obs)


README = Path(__file__).resolve().parents[1] / "README.md"


def test_each_pilot_says_what_flies_each_segment_and_the_readme_says_the_same():
    # the networks fly the approach only: a user reading the README or a run's summary must see that
    rows = {}
    for line in README.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 5 and cells[0].startswith("`") and cells[0].strip("`") in pilot_names():
            rows[cells[0].strip("`")] = dict(zip(SEGMENTS, cells[1:], strict=True))
    assert set(rows) == set(pilot_names())
    for name in pilot_names():
        assert make_pilot(name).flies == rows[name], name
    assert make_pilot("e2e").flies["approach"] == "end-to-end network"
    assert {make_pilot(n).flies["traverse"] for n in pilot_names()} == {EXPERT}


def test_the_readme_gives_the_planners_held_out_errors_beside_the_paper_case():
    metrics = json.loads((shipped_path("planner").parent / "metrics.json").read_text())["planner"]
    text = README.read_text()
    held, paper = metrics["holdout"], metrics["paper_case"]
    for label, figures in (
        ("paper's test case, worst", (paper["max_pos_m"], paper["max_vel_m_s"], paper["max_acc_m_s2"])),
        ("held out (91 trajectories of the training ranges), mean",
         (held["mean_pos_m"], held["mean_vel_m_s"], held["mean_acc_m_s2"])),
        ("held out, worst", (held["max_pos_m"], held["max_vel_m_s"], held["max_acc_m_s2"])),
    ):
        assert f"| {label} | " + " | ".join(f"{v:.3f}" for v in figures) + " |" in text, label


def test_a_run_reports_what_flew_each_segment(tmp_path):
    s = loads_scenarios("description: e2e on a level gap\ngap: {roll_deg: 0}\npilot: e2e\nduration_s: 5\n"
                        "expect: {crosses_gap: false, recovery: false}\n")[0]
    r = run_scenario(s, tmp_path, RunOptions(in_process=True))
    assert r.summary["mode"]["pilot_flies"] == make_pilot("e2e").flies
    assert "approach: end-to-end network; traverse, recovery, hover: expert" in (
        tmp_path / "report.html").read_text().replace("&#x27;", "'")


def test_every_pilot_commands_the_same_from_the_programs_float_observation():
    """The onboard program hands pilots a `FloatObservation` (arrays made when first read): it reads as the
    Observation of the same numbers, and each pilot commands exactly what it commands from that one."""
    gap, plan = _plan()
    for t in (0.3, 1.7, 2.4, 3.0):  # approach (the networks fly it), then the expert's segments
        ref, off = plan.reference(t), (0.05, -0.04, 0.03)
        pos = tuple(float(x + d) for x, d in zip(ref.pos_m, off, strict=True))
        vel = tuple(float(x - 0.5 * d) for x, d in zip(ref.vel_m_s, off, strict=True))
        acc = tuple(float(x) for x in ref.acc_m_s2)
        half = 0.5 * plan.yaw_rad
        quat = (math.cos(half), 0.02, -0.01, math.sin(half))
        lazy = FloatObservation.of_floats(t, pos, vel, acc, quat, gap, plan)
        eager = Observation(t, np.array(pos), np.array(vel), np.array(acc), np.array(euler_from_quat(quat)),
                            gap, plan)
        assert lazy.pos_vel() == (pos, vel)
        for name in ("traditional", "planner_net", "e2e"):
            pilot = make_pilot(name)
            assert pilot.command(FloatObservation.of_floats(t, pos, vel, acc, quat, gap, plan)) == \
                pilot.command(eager), (name, t)
        for field in ("pos_m", "vel_m_s", "acc_m_s2", "euler_rad"):
            assert np.array_equal(getattr(lazy, field), getattr(eager, field))
            assert getattr(lazy, field) is getattr(lazy, field)  # made once
