"""JSBSim aircraft XML for a `VehicleProfile`: mass, inertia, rotor force points, ground contacts, planet.

The generated model has no engines and no aerodynamics: every rotor force and torque, the body drag
and disturbance forces are computed in Python and written each step into ``<external_reactions>``.
JSBSim integrates the rigid body and the ground contacts.

Units: the XML is written in JSBSim's own units (ft, slug, lbf) with exact conversion factors, so the
Python side and JSBSim agree to rounding. Frames: JSBSim's structural frame is x aft, y right, z up;
its body frame is FRD; the profile's body frame is FLU.

The planet is a non-rotating sphere of radius ``PLANET_RADIUS_M`` with surface gravity
``GRAVITY_M_S2`` and no J2 term, so a local tangent plane at latitude 0, longitude 0 is a flat world
to within ``d**2 / (2 R)`` (12.5 um at 50 m) and gravity tilts by ``d / R`` (5e-7 rad at 50 m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from emulator.profile import ROTOR_ANGLES_RAD, VehicleProfile

FT_M = 0.3048  # metres per foot (exact)
LBF_N = 4.4482216152605  # newtons per pound-force (exact)
SLUG_KG = LBF_N / FT_M  # kilograms per slug (lbf s^2 / ft)
JSBSIM_SLUG_TO_LBS = 32.174049  # the factor JSBSim divides an empty weight (lbs) by to get slugs
PLANET_RADIUS_M = 1.0e8  # a large sphere: flat to within d^2 / (2 R)
CONTACT_OMEGA_DT = 0.5  # fastest ground-contact mode times dt: inside the integrators' stability
GROUND_STATIC_FRICTION = 0.8
GROUND_DYNAMIC_FRICTION = 0.5


@dataclass(frozen=True)
class AircraftFiles:
    """The model's name (used for the aircraft folder and file) and its XML text."""

    name: str
    xml: str


@dataclass(frozen=True)
class GroundContacts:
    """Spring-damper ground contacts: points in FLU (m), per-contact spring and damping."""

    points_flu_m: tuple[tuple[float, float, float], ...]
    spring_n_m: float
    damping_n_s_m: float
    rest_deflection_m: float  # spring compression under the vehicle's weight


def ground_contacts(profile: VehicleProfile, gravity_m_s2: float, dt_s: float) -> GroundContacts:
    """Contacts at the eight corners of the body box, as stiff as stable integration allows.

    The fastest mode on the springs is roll or pitch (the corners' lever arms over a light body) or the
    vertical bounce, whichever has the smallest effective mass; it is critically damped at
    ``CONTACT_OMEGA_DT / dt_s`` rad/s. The points sit ``rest_deflection_m`` outside the box top and
    bottom faces, so that under the vehicle's weight the box bottom rests at exactly z = 0.
    """
    m = profile.mass_kg
    ixx, iyy, _ = profile.inertia_kgm2
    lx, ly, lz = (d / 2.0 for d in profile.body_box_m)
    m_eff = min(m, ixx / ly**2, iyy / lx**2)
    omega = CONTACT_OMEGA_DT / dt_s
    total_k = m_eff * omega**2  # four contacts carry the weight
    total_c = 2.0 * m_eff * omega
    rest = m * gravity_m_s2 / total_k
    points = tuple(
        (sx * lx, sy * ly, sz * (lz + rest)) for sz in (-1.0, 1.0) for sx in (1.0, -1.0) for sy in (1.0, -1.0)
    )
    return GroundContacts(points, total_k / 4.0, total_c / 4.0, rest)


def rotor_positions_flu_m(profile: VehicleProfile) -> list[tuple[float, float, float]]:
    """Rotor centres in the body frame FLU (m), in the profile's rotor order."""
    a = profile.arm_length_m
    return [(a * math.cos(th), a * math.sin(th), 0.0) for th in ROTOR_ANGLES_RAD]


def box_corners_flu_m(profile: VehicleProfile) -> list[tuple[float, float, float]]:
    """The four bottom corners of the body box in FLU (m)."""
    lx, ly, lz = (d / 2.0 for d in profile.body_box_m)
    return [(sx * lx, sy * ly, -lz) for sx in (1.0, -1.0) for sy in (1.0, -1.0)]


def _loc_ft(p_flu_m: tuple[float, float, float]) -> str:
    """A FLU point (m) as a structural-frame ``<location>`` (x aft, y right, z up; ft)."""
    x, y, z = (-p_flu_m[0] / FT_M, -p_flu_m[1] / FT_M, p_flu_m[2] / FT_M)
    return f'<location unit="FT"><x>{x:.12g}</x><y>{y:.12g}</y><z>{z:.12g}</z></location>'


def aircraft_xml(
    profile: VehicleProfile, gravity_m_s2: float, dt_s: float, model_name: str = "crossgap_quad"
) -> AircraftFiles:
    """The JSBSim FDM config for ``profile`` under surface gravity ``gravity_m_s2`` (m/s^2), with
    ground contacts tuned for steps of ``dt_s`` (s)."""
    ixx, iyy, izz = (i / (SLUG_KG * FT_M**2) for i in profile.inertia_kgm2)
    mass_slug = profile.mass_kg / SLUG_KG
    radius_ft = PLANET_RADIUS_M / FT_M
    gm_ft3_s2 = gravity_m_s2 / FT_M * radius_ft**2
    ground = ground_contacts(profile, gravity_m_s2, dt_s)
    k_lbf_ft, c_lbf_s_ft = ground.spring_n_m * FT_M / LBF_N, ground.damping_n_s_m * FT_M / LBF_N

    rotors = "\n".join(
        f"""    <force name="rotor{i}" frame="BODY">
      {_loc_ft(p)}
      <direction><x>0</x><y>0</y><z>-1</z></direction>
    </force>"""
        for i, p in enumerate(rotor_positions_flu_m(profile))
    )
    contacts = "\n".join(
        f"""    <contact type="STRUCTURE" name="corner{i}">
      {_loc_ft(p)}
      <static_friction>{GROUND_STATIC_FRICTION}</static_friction>
      <dynamic_friction>{GROUND_DYNAMIC_FRICTION}</dynamic_friction>
      <rolling_friction>{GROUND_DYNAMIC_FRICTION}</rolling_friction>
      <spring_coeff unit="LBS/FT">{k_lbf_ft:.12g}</spring_coeff>
      <damping_coeff unit="LBS/FT/SEC">{c_lbf_s_ft:.12g}</damping_coeff>
      <max_steer unit="DEG">0</max_steer>
      <brake_group>NONE</brake_group>
      <retractable>0</retractable>
    </contact>"""
        for i, p in enumerate(ground.points_flu_m)
    )
    origin = '<location unit="FT"><x>0</x><y>0</y><z>0</z></location>'
    xml = f"""<?xml version="1.0"?>
<fdm_config name="{model_name}" version="2.0" release="ALPHA">
  <fileheader>
    <description>Quadrotor rigid body generated from profile {profile.name}</description>
  </fileheader>
  <planet name="flat-ish">
    <semimajor_axis unit="FT">{radius_ft:.17g}</semimajor_axis>
    <semiminor_axis unit="FT">{radius_ft:.17g}</semiminor_axis>
    <rotation_rate unit="RAD/SEC">0.0</rotation_rate>
    <GM unit="FT3/SEC2">{gm_ft3_s2:.17g}</GM>
    <J2>0.0</J2>
  </planet>
  <metrics>
    <wingarea unit="FT2">1</wingarea>
    <wingspan unit="FT">1</wingspan>
    <chord unit="FT">1</chord>
    <location name="AERORP" unit="FT"><x>0</x><y>0</y><z>0</z></location>
    <location name="EYEPOINT" unit="FT"><x>0</x><y>0</y><z>0</z></location>
    <location name="VRP" unit="FT"><x>0</x><y>0</y><z>0</z></location>
  </metrics>
  <mass_balance>
    <ixx unit="SLUG*FT2">{ixx:.17g}</ixx>
    <iyy unit="SLUG*FT2">{iyy:.17g}</iyy>
    <izz unit="SLUG*FT2">{izz:.17g}</izz>
    <ixy unit="SLUG*FT2">0</ixy>
    <ixz unit="SLUG*FT2">0</ixz>
    <iyz unit="SLUG*FT2">0</iyz>
    <emptywt unit="LBS">{mass_slug * JSBSIM_SLUG_TO_LBS:.17g}</emptywt>
    <location name="CG" unit="FT"><x>0</x><y>0</y><z>0</z></location>
  </mass_balance>
  <ground_reactions>
{contacts}
  </ground_reactions>
  <external_reactions>
{rotors}
    <force name="drag" frame="BODY">
      {origin}
      <direction><x>0</x><y>0</y><z>0</z></direction>
    </force>
    <force name="disturbance" frame="LOCAL">
      {origin}
      <direction><x>0</x><y>0</y><z>0</z></direction>
    </force>
    <moment name="torque" frame="BODY">
      <direction><x>0</x><y>0</y><z>0</z></direction>
    </moment>
  </external_reactions>
  <propulsion/>
  <aerodynamics>
    <axis name="X"/>
    <axis name="Y"/>
    <axis name="Z"/>
    <axis name="ROLL"/>
    <axis name="PITCH"/>
    <axis name="YAW"/>
  </aerodynamics>
</fdm_config>
"""
    return AircraftFiles(name=model_name, xml=xml)
