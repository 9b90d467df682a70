"""The FC's parameters over MAVLink, lockstep over an in-memory link: the whole table, reads by name and
index, sets that take effect at once, refusals that echo the value in force, PX4's bytewise integers,
the .tlog, the parameter file, and what a ground station asks while it connects (FTP, missions)."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
from test_fc_mavlink import HOVER, Bench, of_type

from emulator.fc import FcState
from emulator.fc.n3 import ATTITUDE_THRUST_YAW_ANGLE
from emulator.params import PARAMS, ParamError, param_def, read_param_file
from hil.link.mavlink import PX4_MAIN_OFFBOARD, decode_frame, mav
from hil.link.tlog import read_tlog

REAL32, INT32 = mav.MAV_PARAM_TYPE_REAL32, mav.MAV_PARAM_TYPE_INT32


def as_int(value: float) -> int:
    """A PARAM_VALUE's int32, PX4's bytewise encoding in the float field."""
    return struct.unpack("<i", struct.pack("<f", value))[0]


def int_wire(value: int) -> float:
    return struct.unpack("<f", struct.pack("<i", value))[0]


def param_set(b: Bench, name: str, value: float, ptype: int = REAL32) -> list:
    b.send(b.client.mav.param_set_encode(1, 1, name.encode(), value, ptype))
    return b.run(0.02)


def values(msgs: list, name: str) -> list:
    return [m for m in of_type(msgs, "PARAM_VALUE") if m.param_id == name]


def test_the_whole_table_comes_with_indices_count_and_types():
    b = Bench()
    b.run(0.05)
    b.send(b.client.mav.param_request_list_encode(1, 1))
    got = of_type(b.run(0.05), "PARAM_VALUE")
    assert [m.param_index for m in got] == list(range(len(PARAMS)))
    assert {m.param_count for m in got} == {len(PARAMS)}
    by_name = {m.param_id: m for m in got}
    assert by_name["COM_OF_LOSS_T"].param_value == 1.0 and by_name["COM_OF_LOSS_T"].param_type == REAL32
    act = by_name["COM_OBL_RC_ACT"]
    assert act.param_type == INT32 and as_int(act.param_value) == 5  # hold, then land
    assert by_name["MPC_THR_HOVER"].param_value == pytest.approx(b.vehicle.profile.hover_throttle, rel=1e-6)
    assert by_name["N3_RATE_ATT"].param_value == 50.0
    assert all(len(name) <= 16 for name in by_name)
    # the capability a client reads to decode those integers
    b.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    [ver] = of_type(b.received, "AUTOPILOT_VERSION")
    assert ver.capabilities & mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE


def test_read_by_name_and_by_index_and_unknown_ones_are_told():
    b = Bench()
    b.send(b.client.mav.param_request_read_encode(1, 1, b"MPC_TILTMAX_AIR", -1))
    [m] = of_type(b.run(0.02), "PARAM_VALUE")
    assert (m.param_id, m.param_value, m.param_index) == ("MPC_TILTMAX_AIR", 30.0, 3)
    b.send(b.client.mav.param_request_read_encode(1, 1, b"", 0))
    [m] = of_type(b.run(0.02), "PARAM_VALUE")
    assert m.param_id == "COM_OF_LOSS_T"
    b.send(b.client.mav.param_request_read_encode(1, 1, b"NOPE", -1))
    got = b.run(0.02)
    assert not of_type(got, "PARAM_VALUE")
    [err] = of_type(got, "PARAM_ERROR")
    assert err.error == mav.MAV_PARAM_ERROR_DOES_NOT_EXIST and err.target_system == 255
    assert any("unknown parameter NOPE" in t.text for t in of_type(got, "STATUSTEXT"))
    b.send(b.client.mav.param_request_read_encode(1, 1, b"", len(PARAMS)))
    assert of_type(b.run(0.02), "PARAM_ERROR")


def test_set_takes_effect_at_once_and_the_failsafe_fires_at_the_new_timeout():
    b = Bench()
    [echo] = values(param_set(b, "COM_OF_LOSS_T", 0.5), "COM_OF_LOSS_T")
    assert echo.param_value == 0.5 and b.vehicle.fc.config.failsafe_timeout_s == 0.5
    b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    b.stream(0.3, thrust=1.1 * HOVER)
    b.command(mav.MAV_CMD_DO_SET_MODE, 129, PX4_MAIN_OFFBOARD)
    b.stream(0.5, thrust=1.1 * HOVER)
    assert b.vehicle.fc.state is FcState.OFFBOARD
    last_s = b.vehicle.fc.last_setpoint_s
    b.run(1.0)
    [ev] = [e for e in b.vehicle.fc.events if e.to_state is FcState.FAILSAFE_HOVER]
    assert 0.5 <= ev.time_s - last_s <= 0.5 + 0.1


def test_refusals_echo_the_value_in_force_and_say_why():
    b = Bench()
    param_set(b, "COM_OF_LOSS_T", 0.5)
    for name, value, ptype, why in (
        ("COM_OF_LOSS_T", 99.0, REAL32, "outside 0.1..60 s"),
        ("COM_OF_LOSS_T", float("nan"), REAL32, "finite"),
        ("COM_OF_LOSS_T", int_wire(2), INT32, "is REAL32"),
    ):
        got = param_set(b, name, value, ptype)
        [echo] = values(got, name)
        assert echo.param_value == 0.5, (value, ptype)
        assert any(why in t.text for t in of_type(got, "STATUSTEXT")), why
        assert of_type(got, "PARAM_ERROR")
    assert b.vehicle.fc.config.failsafe_timeout_s == 0.5
    # an enum: only the actions this FC flies, sent as PX4 sends integers
    got = param_set(b, "COM_OBL_RC_ACT", int_wire(3), INT32)
    assert as_int(values(got, "COM_OBL_RC_ACT")[0].param_value) == 5
    assert any("not one of 4 land, 5 hover" in t.text for t in of_type(got, "STATUSTEXT"))
    got = param_set(b, "COM_OBL_RC_ACT", 4.5, REAL32)  # a fraction where an int32 is kept: refused
    assert as_int(values(got, "COM_OBL_RC_ACT")[0].param_value) == 5
    got = param_set(b, "COM_OBL_RC_ACT", int_wire(4), INT32)
    assert as_int(values(got, "COM_OBL_RC_ACT")[0].param_value) == 4
    assert b.vehicle.fc.config.failsafe_action == "land"
    got = param_set(b, "NO_SUCH_PARAM", 1.0)
    assert not of_type(got, "PARAM_VALUE") and of_type(got, "PARAM_ERROR")
    assert b.server.stats.params_refused == 6 and b.server.stats.params_set == 2


def test_range_edges_are_taken_as_float32_carries_them():
    b = Bench()
    for name, edge in (("MPC_THR_HOVER", 0.1), ("MPC_THR_HOVER", 0.8), ("N3_ESC_TOUT", 0.01)):
        got = param_set(b, name, edge)  # on the wire 0.800000012 and 0.00999999978
        assert not of_type(got, "PARAM_ERROR"), name
        assert values(got, name)[-1].param_value == pytest.approx(edge, rel=1e-7)
    assert b.vehicle.fc.config.hover_throttle == 0.8  # held as the documented limit, not past it
    assert b.server.params.get("N3_ESC_TOUT") == 0.01
    got = param_set(b, "MPC_THR_HOVER", 0.8001)  # past the edge by more than float32's rounding
    assert of_type(got, "PARAM_ERROR") and b.vehicle.fc.config.hover_throttle == 0.8


def test_an_int32_set_as_a_whole_real32_is_taken_and_echoed_as_int32():
    b = Bench()
    got = param_set(b, "COM_OBL_RC_ACT", 4.0, REAL32)  # as MAVProxy's `param load` sends it
    [echo] = values(got, "COM_OBL_RC_ACT")
    assert echo.param_type == INT32 and as_int(echo.param_value) == 4
    assert b.vehicle.fc.config.failsafe_action == "land" and b.server.stats.params_set == 1
    got = param_set(b, "N3_ESC_FS_ACT", 7.0, REAL32)  # whole, but not a choice: refused by range
    assert any("not one of" in t.text for t in of_type(got, "STATUSTEXT"))


def test_failsafe_action_land_lands_at_once():
    b = Bench()
    param_set(b, "COM_OBL_RC_ACT", int_wire(4), INT32)
    b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    b.stream(0.3, thrust=1.3 * HOVER)
    b.command(mav.MAV_CMD_DO_SET_MODE, 129, PX4_MAIN_OFFBOARD)
    b.stream(1.0, thrust=1.3 * HOVER)
    b.run(1.2)
    states = [e.to_state for e in b.vehicle.fc.events]
    assert FcState.FAILSAFE_LAND in states and FcState.FAILSAFE_HOVER not in states


def test_telemetry_rate_and_limits_follow_their_parameters():
    b = Bench()
    param_set(b, "N3_RATE_ATT", 10.0)
    assert len(of_type(b.run(1.0), "ATTITUDE")) == pytest.approx(10, abs=1)
    param_set(b, "N3_RATE_ATT", 0.0)
    assert not of_type(b.run(0.5), "ATTITUDE")
    # SET_MESSAGE_INTERVAL changes the same setting: the parameter reads it back
    b.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, 40000)
    b.send(b.client.mav.param_request_read_encode(1, 1, b"N3_RATE_ATT", -1))
    assert values(b.run(0.02), "N3_RATE_ATT")[0].param_value == pytest.approx(25.0)
    # the setpoint tilt limit: a 40 deg setpoint is flown at the new 20 deg
    param_set(b, "N3_SP_TILT_MAX", 20.0)
    import math

    now = b.clock.now_s()
    target = b.vehicle.fc.set_setpoint_values(ATTITUDE_THRUST_YAW_ANGLE, 40.0, 0.0, 50.0, 0.0, now)
    assert math.degrees(target.roll_rad) == pytest.approx(20.0, abs=0.01)


def test_hover_throttle_is_what_the_fc_hover_controller_assumes():
    b = Bench()
    before = b.vehicle.fc.hold_params.copy()
    param_set(b, "MPC_THR_HOVER", 0.5)
    p = b.vehicle.fc.hold_params
    assert p[4] == pytest.approx(0.5 * b.vehicle.profile.max_total_thrust_n / 9.80665)
    assert p[4] != before[4] and p is b.vehicle.fc.hold_params  # changed in place (batched steppers)


def test_changes_are_in_the_tlog(tmp_path: Path):
    b = Bench(tlog=tmp_path / "p.tlog")
    param_set(b, "COM_OF_LOSS_T", 0.5)
    param_set(b, "COM_OF_LOSS_T", 99.0)
    b.tlog.close()
    msgs = [decode_frame(f) for _, f in read_tlog(tmp_path / "p.tlog")]
    sets = [m.param_value for m in of_type(msgs, "PARAM_SET")]
    echoed = [m.param_value for m in of_type(msgs, "PARAM_VALUE")]
    assert sets == [0.5, 99.0] and echoed == [0.5, 0.5]


def test_ftp_is_naked_at_once_and_missions_are_empty():
    b = Bench()
    payload = [7, 0, 0, mav.MAV_FTP_OPCODE_OPENFILERO, 20, 0, 0, 0, 0, 0, 0, 0, *b"@PARAM/param.pck"]
    b.send(b.client.mav.file_transfer_protocol_encode(0, 1, 1, payload + [0] * (251 - len(payload))))
    b.send(b.client.mav.mission_request_list_encode(1, 1, mav.MAV_MISSION_TYPE_FENCE))
    got = b.run(0.002)
    [ftp] = of_type(got, "FILE_TRANSFER_PROTOCOL")
    seq, opcode, size, req, err = ftp.payload[0] | ftp.payload[1] << 8, *ftp.payload[3:6], ftp.payload[12]
    assert (seq, opcode, size, req) == (8, mav.MAV_FTP_OPCODE_NAK, 1, mav.MAV_FTP_OPCODE_OPENFILERO)
    assert err == mav.MAV_FTP_ERR_FILENOTFOUND and ftp.target_system == 255
    [count] = of_type(got, "MISSION_COUNT")
    assert count.count == 0 and count.mission_type == mav.MAV_MISSION_TYPE_FENCE


def test_parameter_file_loaded_and_written_back_on_request(tmp_path: Path):
    path = tmp_path / "fc.params"
    path.write_text("# mine\nCOM_OF_LOSS_T 0.5\n1\t1\tMPC_TILTMAX_AIR\t25\t9\n")  # MAVProxy and QGC lines
    assert read_param_file(path) == {"COM_OF_LOSS_T": 0.5, "MPC_TILTMAX_AIR": 25.0}
    from emulator.servers.mavlink_server import ServerConfig

    b = Bench()
    b.server.config = ServerConfig(param_file=str(path))
    [ack] = b.command(mav.MAV_CMD_PREFLIGHT_STORAGE, 0)  # read
    assert ack.result == mav.MAV_RESULT_ACCEPTED and b.vehicle.fc.config.hover_max_tilt_deg == 25.0
    param_set(b, "N3_FS_HOVER_T", 7.0)
    [ack] = b.command(mav.MAV_CMD_PREFLIGHT_STORAGE, 1)  # write
    assert ack.result == mav.MAV_RESULT_ACCEPTED
    saved = read_param_file(path)
    assert len(saved) == len(PARAMS) and saved["N3_FS_HOVER_T"] == 7.0 and saved["COM_OF_LOSS_T"] == 0.5
    [ack] = b.command(mav.MAV_CMD_PREFLIGHT_STORAGE, 2)  # defaults
    assert b.vehicle.fc.config.failsafe_hover_s == 5.0 and b.vehicle.fc.config.failsafe_timeout_s == 1.0
    b.server.config = ServerConfig()
    [ack] = b.command(mav.MAV_CMD_PREFLIGHT_STORAGE, 1)
    assert ack.result == mav.MAV_RESULT_DENIED


def test_bad_parameter_files_name_the_line(tmp_path: Path):
    for text, why in (
        ("COM_OF_LOSS_T\n", ":1: expected 'NAME VALUE'"),
        ("COM_OF_LOSS_T abc\n", ":1: COM_OF_LOSS_T: expected a number"),
        ("\nCOM_OF_LOS_T 1\n", ":2: unknown parameter 'COM_OF_LOS_T' (did you mean COM_OF_LOSS_T?)"),
        ("COM_OBL_RC_ACT 4.5\n", ":1: COM_OBL_RC_ACT: expected an integer"),
    ):
        path = tmp_path / "bad.params"
        path.write_text(text)
        with pytest.raises(ValueError, match=why.replace("(", r"\(").replace(")", r"\)").replace("?", r"\?")):
            read_param_file(path)


def test_each_parameter_default_is_its_settings_default():
    b = Bench()
    params = b.server.params
    for _, p, v in params.items():
        assert v == pytest.approx(p.default(b.vehicle.fc), rel=1e-6), p.name
        assert p.lo <= v <= p.hi, p.name
    with pytest.raises(ParamError, match="did you mean"):
        param_def("COM_OF_LOSST")


def test_the_readme_shows_the_table_as_it_is():
    from emulator.params import describe

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    missing = [row for row in describe() if row not in readme]
    assert missing == []
