"""The emulator assembled: vehicle (physics + FC), the gap world, the FC's server on the command link
(by protocol name, `emulator.servers.registry.FC_SERVERS`: MAVLink, DJI's OPEN protocol) and mocap over UWB on
the mocap link, one clock for all. `hil fc` (real time) and the runner's emulator side (simulated
time) both build theirs here and add their own loop around it."""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from typing import Any

import numpy as np

from emulator.fc import FcConfig
from emulator.mocap import MocapConfig
from emulator.mocap_link import MocapLinkServer
from emulator.mocap_link import compile_kernels as compile_mocap_link
from emulator.physics.state import VehicleState
from emulator.profile import VehicleProfile
from emulator.servers.registry import FC_SERVERS, FcServer, ServerOptions, make_server
from emulator.uwb import UwbConfig
from emulator.vehicle import EmulatedVehicle
from emulator.world import Gap, LabVolume, World
from hil.link.clock import Clock
from hil.link.mavlink import SIGNING_EPOCH_UNIX_S
from hil.link.tlog import TlogWriter
from hil.link.transport import Transport


@dataclass(frozen=True)
class Emulator:
    """The parts of one assembled emulator."""

    vehicle: EmulatedVehicle
    world: World | None  # None: no gap to watch
    codec: Any  # the server's codec
    server: FcServer
    mocap: MocapLinkServer | None  # None: no mocap link


def warm_up(profile: VehicleProfile) -> None:
    """Compile (or load from numba's cache) the kernels an emulator of ``profile`` runs (the vehicle's
    own steps, the world's checks, the mocap exposure, each protocol's server's), so that a wall clock
    started afterwards does not pay for them."""
    EmulatedVehicle(profile).compile_kernels()
    World.for_profile(Gap(), LabVolume(), profile).compile_kernels()
    compile_mocap_link()  # (its exposure kernel and its radio's step, built with the link)
    for server in FC_SERVERS.values():  # (a server compiles its kernels as it is built, after the clock)
        if server.warm_up is not None:
            server.warm_up()


def assemble(
    profile: VehicleProfile,
    command_link: Transport,
    clock: Clock,
    *,
    initial_state: VehicleState,
    backend: str = "native",
    fc_config: FcConfig | None = None,
    gap: Gap | None = None,
    lab: LabVolume | None = None,
    mocap_link: Transport | None = None,
    mocap_rng: np.random.Generator | None = None,
    mocap_config: MocapConfig | None = None,
    uwb_config: UwbConfig | None = None,
    system_id: int = 1,
    raw_ids: Collection[int] = (),
    tlog: TlogWriter | None = None,
    signing_key: bytes | None = None,
    signing_epoch_unix_s: float = SIGNING_EPOCH_UNIX_S,
    protocol: str = "mavlink",
    protocol_config: object | None = None,
) -> Emulator:
    """Build the emulator (see the module doc); ``mocap_rng`` is needed with a mocap link;
    ``protocol_config``: the settings of the protocol's server (`emulator.servers.registry.server_config`).
    A wall clock should start after `warm_up`."""
    vehicle = EmulatedVehicle(profile, backend=backend, config=fc_config, initial_state=initial_state)
    world = None if gap is None else World.for_profile(gap, lab or LabVolume(), profile)
    server = make_server(protocol, vehicle, command_link, clock, ServerOptions(
        system_id, raw_ids, tlog, signing_key, signing_epoch_unix_s, protocol_config))
    mocap = None
    if mocap_link is not None:
        if mocap_rng is None:
            raise ValueError("a mocap link needs mocap_rng")
        mocap = MocapLinkServer(mocap_link, clock, mocap_rng, mocap_config, uwb_config)
    return Emulator(vehicle, world, server.codec, server, mocap)
