"""Vehicle profiles: the shipped YAML files load, match their sources, and bad files are named errors."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from importlib import resources
from pathlib import Path

import pytest
import yaml

from emulator.profile import GRAVITY_M_S2, ProfileError, builtin_profiles, load_profile


def _builtin_yaml(name: str) -> dict:
    return yaml.safe_load((resources.files("emulator") / "profiles" / f"{name}.yaml").read_text())


def _write(tmp_path: Path, data: dict | str) -> Path:
    path = tmp_path / "custom.yaml"
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return path


def test_builtin_profiles_load() -> None:
    assert {"n3_tx2", "f450"} <= set(builtin_profiles())
    for name in builtin_profiles():
        profile = load_profile(name)
        assert profile.name == name
        assert profile.source_notes
        assert 0.0 < profile.hover_throttle < 1.0


def test_n3_tx2_is_the_papers_platform() -> None:
    p = load_profile("n3_tx2")
    assert p.mass_kg == 0.9
    assert p.max_tilt_deg >= 60.0  # the paper flew through a 60 deg gap
    thrust_to_weight = p.max_total_thrust_n / (p.mass_kg * GRAVITY_M_S2)
    assert 2.5 <= thrust_to_weight <= 3.0
    # Full throttle must hold altitude at 60 deg of tilt: T cos(60) > m g.
    assert p.max_total_thrust_n * math.cos(math.radians(60)) > p.mass_kg * GRAVITY_M_S2
    assert 0.35 <= 2 * p.arm_length_m <= 0.55  # a 450 mm-class frame


def test_f450_matches_jsbsim_aircraft_files() -> None:
    import jsbsim  # the optional engine whose data this profile copies
    folder = Path(jsbsim.get_default_root_dir()) / "aircraft" / "F450"
    mass = ET.parse(folder / "Mass.xml").getroot()
    p = load_profile("f450")
    assert p.mass_kg == pytest.approx(float(mass.findtext("emptywt")))
    for axis, value in zip(("ixx", "iyy", "izz"), p.inertia_kgm2, strict=True):
        assert value == pytest.approx(float(mass.findtext(axis)))
    propulsion = ET.parse(folder / "Propulsion.xml").getroot()
    for loc in propulsion.iter("location"):
        arm = math.hypot(float(loc.findtext("x")), float(loc.findtext("y")))
        assert p.arm_length_m == pytest.approx(arm, rel=1e-4)
    prop = ET.parse(Path(jsbsim.get_default_root_dir()) / "engine" / "DJI_9450.xml").getroot()
    diameter_m = float(prop.findtext("diameter")) * 0.0254
    ct0 = float(prop.find("table[@name='C_THRUST']/tableData").text.split()[1])
    assert p.thrust_coeff_n_s2 == pytest.approx(ct0 * 1.225 * diameter_m**4 / (4 * math.pi**2), rel=1e-3)


def test_load_by_path_equals_load_by_name(tmp_path: Path) -> None:
    path = _write(tmp_path, _builtin_yaml("n3_tx2"))
    assert load_profile(path) == load_profile("n3_tx2")


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda d: d.pop("mass_kg"), "mass_kg"),
        (lambda d: d.update(arm_length_m="long"), "arm_length_m"),
        (lambda d: d.update(inertia_kgm2=[0.01, 0.01]), "inertia_kgm2"),
        (lambda d: d.update(mass_kg=-0.9), "mass_kg"),
        (lambda d: d.update(wingspan_m=0.3), "wingspan_m"),
        (lambda d: d.update(mass_kg=3.0), "max_thrust_per_rotor_n"),  # too heavy to fly
        (lambda d: d.update(max_tilt_deg=95.0), "max_tilt_deg"),
        (lambda d: d.update(linear_drag_n_s_m=[0.1, -0.1, 0.1]), "linear_drag_n_s_m"),
    ],
    ids=["missing", "wrong-type", "wrong-length", "negative-mass", "unknown", "too-heavy", "tilt", "drag"],
)
def test_malformed_profile_names_file_and_field(tmp_path: Path, change, field: str) -> None:
    data = _builtin_yaml("n3_tx2")
    change(data)
    path = _write(tmp_path, data)
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    assert info.value.field == field
    assert str(path) in str(info.value) and field in str(info.value)


def test_bad_yaml_and_missing_file(tmp_path: Path) -> None:
    path = _write(tmp_path, "name: [unclosed\nmass_kg: 1\n")
    with pytest.raises(ProfileError, match=r"custom\.yaml") as info:
        load_profile(path)
    assert info.value.field == "<yaml>"
    with pytest.raises(ProfileError, match="cannot read"):
        load_profile(tmp_path / "absent.yaml")
    with pytest.raises(ProfileError, match="no built-in profile"):
        load_profile("no_such_vehicle")


def test_with_changes_is_validated() -> None:
    p = load_profile("n3_tx2")
    assert p.with_changes(mass_kg=1.0).mass_kg == 1.0
    with pytest.raises(ProfileError, match="mass_kg"):
        p.with_changes(mass_kg=0.0)


def test_thrust_percent_round_trip() -> None:
    p = load_profile("n3_tx2")
    hover_n = p.mass_kg * GRAVITY_M_S2
    percent = p.force_to_thrust_percent(hover_n)
    assert 30.0 < percent < 45.0
    assert p.thrust_percent_to_force_n(percent) == pytest.approx(hover_n)


def test_the_fc_flies_the_inertia_it_is_tuned_for(tmp_path: Path) -> None:
    """``fc_inertia_kgm2`` (optional) is what the FC's inner loop believes; the physics keeps the
    airframe's ``inertia_kgm2``. Left out, the FC knows the airframe's; a bad value names the field."""
    import numpy as np

    from emulator.fc.inner_loop import InnerLoop
    from emulator.fc.tuning import fc_gains
    from emulator.physics.native import NativeBackend

    p = load_profile("n3_tx2")
    assert p.fc_inertia_kgm2 is None and p.fc_tuned_inertia_kgm2 == p.inertia_kgm2
    wrong = p.with_changes(fc_inertia_kgm2=(0.002, 0.002, 0.0137))
    assert wrong.fc_tuned_inertia_kgm2 == (0.002, 0.002, 0.0137)
    assert wrong.with_changes(fc_inertia_kgm2=None) == p
    # the FC asks for the torque its inertia needs: a quarter-size belief gives a smaller roll torque
    q, w = np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3)
    right = InnerLoop(p, fc_gains(p).inner).update(q, w, 0.3, 0.0, math.pi / 2, 8.8).copy()
    low = InnerLoop(wrong, fc_gains(wrong).inner).update(q, w, 0.3, 0.0, math.pi / 2, 8.8).copy()
    assert fc_gains(wrong) == fc_gains(p)  # the same tuning rule: only the torque it asks for differs
    assert np.ptp(low) < 0.5 * np.ptp(right)
    assert NativeBackend(wrong)._params.tolist() == NativeBackend(p)._params.tolist()  # the airframe
    shipped = Path(__file__).parent.parent / "scenarios" / "vehicles" / "n3_tx2_fc_inertia_low.yaml"
    assert load_profile(shipped).fc_tuned_inertia_kgm2[0] == pytest.approx(p.inertia_kgm2[0] / 4, rel=0.01)
    bad = tmp_path / "bad.yaml"
    data = yaml.safe_load((resources.files("emulator") / "profiles" / "n3_tx2.yaml").read_text())
    bad.write_text(yaml.safe_dump({**data, "fc_inertia_kgm2": [0.1, -1, 0.1]}))
    with pytest.raises(ProfileError, match="fc_inertia_kgm2"):
        load_profile(bad)


def test_a_profile_is_parsed_once_per_text_and_an_edited_file_is_read_again(tmp_path):
    assert load_profile("n3_tx2") is load_profile("n3_tx2")  # (a suite loads it run after run)
    f = tmp_path / "quad.yaml"
    text = (Path(__file__).resolve().parents[1] / "emulator" / "profiles" / "n3_tx2.yaml").read_text()
    f.write_text(text)
    first = load_profile(f)
    f.write_text(text.replace("mass_kg: 0.9", "mass_kg: 1.0"))
    assert first.mass_kg == 0.9 and load_profile(f).mass_kg == 1.0
