"""100k random and mutated MAVLink frames thrown at the FC over an in-memory link: nothing crashes,
everything is counted, and the vehicle still flies the setpoints that follow."""

from __future__ import annotations

import math
import struct

import numpy as np

from emulator.fc import FcState
from emulator.profile import GRAVITY_M_S2, load_profile
from emulator.servers.mavlink_server import MavlinkServer
from emulator.vehicle import EmulatedVehicle
from hil.link import MemoryTransport, SimClock
from hil.link.mavlink import PX4_MAIN_OFFBOARD, MavlinkCodec, mav, quat_from_euler

PROFILE = load_profile("n3_tx2")
HOVER = PROFILE.mass_kg * GRAVITY_M_S2 / PROFILE.n3_full_thrust_n
N_FRAMES = 100_000
CHUNK_BYTES = 16_000  # well under the memory link's 64 KiB per direction
SPECIAL = [math.nan, math.inf, -math.inf, 0.0, -1.0, 1.0, 2.0, 1e30, -1e30, 0.5]
COMMANDS = [400, 176, 21, 22, 511, 512, 520, 519, 0, 65535]
MSG_IDS = sorted(mav.mavlink_map)


def rand_float(rng: np.random.Generator) -> float:
    return float(rng.choice(SPECIAL)) if rng.random() < 0.5 else float(rng.normal(0, 100))


def raw_frame(msg_id: int, payload: bytes, seq: int, sysid: int = 255, compid: int = 190) -> bytes:
    """A MAVLink 2 frame with a correct CRC for ``msg_id`` (known or not) and any payload."""
    header = struct.pack(
        "<BBBBBBBHB", 0xFD, len(payload), 0, 0, seq & 0xFF, sysid, compid, msg_id & 0xFFFF, msg_id >> 16
    )
    extra = mav.mavlink_map[msg_id].crc_extra if msg_id in mav.mavlink_map else 0
    crc = mav.x25crc(header[1:] + payload + bytes([extra])).crc
    return header + payload + struct.pack("<H", crc)


def make_frames(rng: np.random.Generator, encoder: mav.MAVLink) -> list[bytes]:
    frames: list[bytes] = []
    for i in range(N_FRAMES):
        kind = rng.integers(0, 7)
        if kind == 0:  # garbage bytes
            frames.append(rng.bytes(int(rng.integers(1, 40))))
        elif kind == 1:  # any known message with a random payload and a valid CRC
            msg_id = int(rng.choice(MSG_IDS))
            frames.append(raw_frame(msg_id, rng.bytes(int(rng.integers(1, 60))), i))
        elif kind == 2:  # unknown message id
            frames.append(raw_frame(int(rng.integers(20000, 2**24)), rng.bytes(int(rng.integers(1, 30))), i))
        else:  # well-formed setpoints and commands with hostile values, some then mutated
            if kind in (3, 4):
                q = [
                    rand_float(rng) if rng.random() < 0.3 else x
                    for x in quat_from_euler(*rng.normal(0, 1, 3))
                ]
                msg = encoder.set_attitude_target_encode(
                    0,
                    int(rng.choice([0, 1, 1, 1, 7])),
                    1,
                    int(rng.integers(0, 256)),
                    q,
                    rand_float(rng),
                    rand_float(rng),
                    rand_float(rng),
                    rand_float(rng),
                )
            else:
                msg = encoder.command_long_encode(
                    int(rng.choice([0, 1, 1, 9])),
                    int(rng.choice([0, 1, 1, 50])),
                    int(rng.choice(COMMANDS)),
                    0,
                    *(
                        rand_float(rng) if rng.random() < 0.5 else float(rng.integers(-2, 260))
                        for _ in range(7)
                    ),
                )
            frame = bytearray(msg.pack(encoder))
            if kind == 6:  # mutate: flip bytes, or truncate
                if rng.random() < 0.5:
                    for _ in range(int(rng.integers(1, 4))):
                        frame[int(rng.integers(0, len(frame)))] ^= int(rng.integers(1, 256))
                else:
                    frame = frame[: int(rng.integers(1, len(frame)))]
            frames.append(bytes(frame))
    return frames


def test_hundred_thousand_hostile_frames_then_a_normal_flight():
    rng = np.random.default_rng(20190430)
    clock = SimClock()
    fc_end, attacker = MemoryTransport.pair()
    vehicle = EmulatedVehicle(PROFILE)
    server = MavlinkServer(vehicle, MavlinkCodec(fc_end, clock, 1, 1))
    client = MavlinkCodec(attacker, clock, 255, 190)
    frames = make_frames(rng, client.mav)

    def tick(dt_s: float = 0.001) -> list:
        clock.advance_to(round(clock.now_s() + dt_s, 6))
        server.poll(clock.now_s())
        vehicle.step_to(clock.now_s())
        return client.receive()

    buf = bytearray()
    for f in frames:
        buf += f
        if len(buf) >= CHUNK_BYTES:
            attacker.send(bytes(buf))
            buf.clear()
            tick()
    attacker.send(bytes(buf))
    tick()

    codec, stats = server.codec.stats, server.stats
    assert stats.handler_errors == 0
    assert codec.garbage_bytes > 10_000 and codec.bad_crc > 1000 and codec.unknown_msg_id > 1000
    assert codec.malformed > 0 and codec.frames_received > 30_000
    assert stats.setpoints_rejected > 1000 and stats.foreign_target > 1000
    assert stats.commands_accepted + stats.commands_denied + stats.commands_unsupported > 1000

    # what follows is a normal flight: force a disarm, then arm, stream, take authority, climb
    for _ in range(30):  # the attack may have left half a frame in the parser: a few frames resync it
        client.send(client.mav.heartbeat_encode(6, 8, 0, 0, 0))
    client.send(client.mav.command_long_encode(1, 1, 400, 0, 0, 21196, 0, 0, 0, 0, 0))
    client.send(client.mav.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
    acks = []
    q = list(quat_from_euler(0.0, 0.0, 0.0))
    for i in range(20):  # 0.4 s of setpoints at 50 Hz, authority requested after 0.2 s
        client.send(client.mav.set_attitude_target_encode(0, 1, 1, 7, q, 0, 0, 0, 1.3 * HOVER))
        if i == 10:
            client.send(client.mav.command_long_encode(1, 1, 176, 0, 129, PX4_MAIN_OFFBOARD, 0, 0, 0, 0, 0))
        acks += [(m.command, m.result) for m in tick(0.02) if m.get_type() == "COMMAND_ACK"]
    assert (400, mav.MAV_RESULT_ACCEPTED) in acks and (176, mav.MAV_RESULT_ACCEPTED) in acks
    assert vehicle.fc.state is FcState.OFFBOARD
    z0 = vehicle.state.pos_m[2]
    for _ in range(50):
        client.send(client.mav.set_attitude_target_encode(0, 1, 1, 7, q, 0, 0, 0, 1.3 * HOVER))
        for _ in range(20):
            tick()
    assert vehicle.state.pos_m[2] - z0 > 0.5 and vehicle.state.vel_m_s[2] > 1.0
    assert abs(vehicle.state.pos_m[0]) < 0.2 and abs(vehicle.state.pos_m[1]) < 0.2
