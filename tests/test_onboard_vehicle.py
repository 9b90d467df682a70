"""The onboard program's own configuration of its vehicle (policies.vehicle): built-in files, bad files
named with the field, the command line's overrides, and the pilots built with its mass and tilt limit."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import pytest

from policies.onboard.cli import add_arguments, config_from_args
from policies.onboard.pilots import PILOTS, PilotContext, make_pilot
from policies.vehicle import DEFAULT_VEHICLE, load_vehicle, vehicle_names


def config(*options: str):
    p = argparse.ArgumentParser()
    add_arguments(p)
    return config_from_args(p.parse_args(["--command-link", "memory", "--mocap-link", "memory", *options]))


def test_built_in_vehicles():
    assert {"n3_tx2", "f450"} <= set(vehicle_names())
    f450 = load_vehicle("f450")
    assert (f450.mass_kg, f450.full_thrust_n, f450.max_tilt_deg) == (1.4, 62.88, 65.0)


def test_the_command_line_takes_the_vehicle_and_overrides_single_fields():
    default = config()
    assert (default.mass_kg, default.full_thrust_n, default.max_tilt_deg, default.control_lead_s) == (
        0.9, 24.0, 75.0, 0.06)
    f450 = config("--vehicle", "f450")
    assert (f450.mass_kg, f450.full_thrust_n, f450.max_tilt_deg, f450.control_lead_s) == (
        1.4, 62.88, 65.0, 0.0925)
    c = config("--vehicle", "f450", "--mass", "1.5", "--max-tilt", "50", "--control-lead-ms", "70")
    assert (c.mass_kg, c.full_thrust_n, c.max_tilt_deg, c.control_lead_s) == (1.5, 62.88, 50.0, 0.07)


def test_the_traverse_lead_comes_from_the_vehicle_where_its_file_gives_one(tmp_path):
    assert config().traverse_lead_m == 0.25  # the n3_tx2's (its file gives none: the default)
    assert config("--vehicle", "f450").traverse_lead_m == 0.4  # its slower attitude loop, longer body
    assert config("--vehicle", "f450", "--traverse-lead", "0.3").traverse_lead_m == 0.3
    f = tmp_path / "v.yaml"
    f.write_text(GOOD + "traverse_lead_m: 0.35\n")
    assert load_vehicle(f).traverse_lead_m == 0.35


GOOD = ("name: x\nmass_kg: 1\nfull_thrust_n: 30\nmax_tilt_deg: 60\ncontrol_lead_s: 0.1\n"
        "body_box_m: [0.5, 0.5, 0.2]\n")


@pytest.mark.parametrize(
    ("text", "words"),
    [
        (GOOD.replace("control_lead_s: 0.1\n", ""), "missing fields \\['control_lead_s'\\]"),
        (GOOD + "mas: 2\n", "unknown fields \\['mas'\\]"),
        (GOOD.replace("mass_kg: 1", "mass_kg: 4"), "cannot hold 4 kg"),
        (GOOD.replace("max_tilt_deg: 60", "max_tilt_deg: 95"), "max_tilt_deg"),
        (GOOD.replace("mass_kg: 1", "mass_kg: heavy"), "mass_kg"),
        (GOOD.replace("control_lead_s: 0.1", "control_lead_s: 0.5"), "control_lead_s"),
        (GOOD.replace("[0.5, 0.5, 0.2]", "[0.5, 0.5]"), "body_box_m must be 3 positive lengths"),
        (GOOD + "traverse_lead_m: 0\n", "traverse_lead_m must be in \\(0, 1\\] m"),
        ("[1, 2]\n", "expected a mapping"),
    ],
)
def test_a_bad_file_is_an_error_naming_it_and_the_field(tmp_path, text, words):
    f = tmp_path / "v.yaml"
    f.write_text(text)
    with pytest.raises(ValueError, match=words) as info:
        load_vehicle(f)
    assert str(f) in str(info.value)
    with pytest.raises(ValueError, match="no onboard vehicle configuration 'nope'"):
        load_vehicle("nope")
    f.write_text(GOOD)
    assert load_vehicle(f).mass_kg == 1.0


@pytest.mark.parametrize("pilot", PILOTS.names())
def test_pilots_fly_with_the_vehicles_mass_and_tilt_limit(pilot):
    p = make_pilot(pilot, PilotContext(mass_kg=1.4, full_thrust_n=62.88, max_tilt_deg=40.0))
    expert = getattr(p, "controller", None) or p.expert
    assert expert.mass_kg == 1.4
    assert expert.gains.tilt_max_rad == pytest.approx(math.radians(40.0))


def test_a_configuration_is_parsed_once_per_text_and_an_edited_file_is_read_again(tmp_path):
    assert load_vehicle(DEFAULT_VEHICLE) is load_vehicle(DEFAULT_VEHICLE)
    f = tmp_path / "quad.onboard.yaml"
    shipped = Path(__file__).resolve().parents[1] / "policies" / "vehicles" / f"{DEFAULT_VEHICLE}.yaml"
    text = shipped.read_text(encoding="utf-8")
    f.write_text(text)
    first = load_vehicle(f)
    f.write_text(text.replace(f"mass_kg: {first.mass_kg}", "mass_kg: 1.25"))
    assert load_vehicle(f).mass_kg == 1.25 != first.mass_kg
