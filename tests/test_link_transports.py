"""Back-to-back tests of every link transport: one suite over every pair, then each one's specifics."""

from __future__ import annotations

import os
import select
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import serial

from hil.link import (
    EndpointSpec,
    LinkError,
    MemoryTransport,
    PtyTransport,
    SerialTransport,
    SimClock,
    TcpTransport,
    Transport,
    UartModel,
    UartTransport,
    UdpTransport,
    open_link,
    parse_endpoint,
)

# --- pairs: (a, b) where a is the fc-style end (creates/binds/listens) and b the one that connects --


def _memory() -> tuple[Transport, Transport]:
    return MemoryTransport.pair()


def _pty_serial() -> tuple[Transport, Transport]:
    a = PtyTransport.create(921600)
    return a, SerialTransport(a.endpoint, 921600)


def _udp() -> tuple[Transport, Transport]:
    a = UdpTransport.server("127.0.0.1", 0)
    b = UdpTransport.client("127.0.0.1", a.local_address[1])
    b.send(b"\x00")  # a UDP server learns where to reply from the first datagram
    assert a.recv(1.0) == b"\x00"
    return a, b


def _tcp() -> tuple[Transport, Transport]:
    a = TcpTransport.server("127.0.0.1", 0)
    return a, TcpTransport.client("127.0.0.1", int(a.endpoint.rsplit(":", 1)[1]))


def _uart_memory() -> tuple[Transport, Transport]:
    return UartTransport.pair(baud=3_000_000, tx_buffer_bytes=8192)


PAIRS: dict[str, Callable[[], tuple[Transport, Transport]]] = {
    "memory": _memory,
    "pty-serial": _pty_serial,
    "udp": _udp,
    "tcp": _tcp,
    "uart-memory": _uart_memory,
}

# What the survivor sees when the other end disappears: recv ("empty": b"" after the timeout,
# "raises": LinkError) and send ("dropped": counted as dropped, "accepted": taken, lost later,
# "raises": LinkError). Keys: (pair, which end closes).
PEER_GONE: dict[tuple[str, str], tuple[str, str]] = {
    ("memory", "a"): ("empty", "dropped"),
    ("memory", "b"): ("empty", "dropped"),
    ("pty-serial", "a"): ("raises", "raises"),  # the device vanished under the serial port
    ("pty-serial", "b"): ("empty", "accepted"),  # the pty buffers until its kernel buffer is full
    ("udp", "a"): ("empty", "accepted"),  # UDP cannot know the peer is gone
    ("udp", "b"): ("empty", "accepted"),
    ("tcp", "a"): ("raises", "raises"),  # the client learns the server is gone
    ("tcp", "b"): ("empty", "dropped"),  # the server waits for the next client
    ("uart-memory", "a"): ("empty", "accepted"),  # the UART takes it; the cable drops it
    ("uart-memory", "b"): ("empty", "accepted"),
}


@pytest.fixture(params=list(PAIRS))
def pair(request: pytest.FixtureRequest) -> Iterator[tuple[Transport, Transport]]:
    a, b = PAIRS[request.param]()
    try:
        yield a, b
    finally:
        a.close()
        b.close()


def recv_exactly(t: Transport, n: int, timeout_s: float = 2.0) -> bytes:
    """Read until ``n`` bytes arrived or ``timeout_s`` passed."""
    got = bytearray()
    deadline = time.monotonic() + timeout_s
    while len(got) < n and time.monotonic() < deadline:
        got += t.recv(max(0.0, deadline - time.monotonic()), max_bytes=n - len(got))
    return bytes(got)


# --- the back-to-back suite --------------------------------------------------------------------


def test_messages_arrive_both_ways_in_order(pair: tuple[Transport, Transport]) -> None:
    a, b = pair
    for i in range(20):
        msg = f"fc->onboard {i};".encode()
        assert a.send(msg) == len(msg)
        assert recv_exactly(b, len(msg)) == msg
        reply = f"onboard->fc {i};".encode()
        assert b.send(reply) == len(reply)
        assert recv_exactly(a, len(reply)) == reply


@pytest.mark.parametrize("direction", ["a->b", "b->a"])
def test_64_kib_in_chunks_arrives_complete(pair: tuple[Transport, Transport], direction: str) -> None:
    a, b = pair
    src, dst = (a, b) if direction == "a->b" else (b, a)
    payload = np.random.default_rng(7).integers(0, 256, 65536, dtype=np.uint8).tobytes()
    got = bytearray()
    for start in range(0, len(payload), 1024):
        chunk = payload[start : start + 1024]
        assert src.send(chunk) == len(chunk)
        got += recv_exactly(dst, len(chunk))
    assert len(got) == len(payload)
    assert bytes(got) == payload


def test_every_byte_value_passes_unchanged(pair: tuple[Transport, Transport]) -> None:
    """Control characters a cooked tty would eat or translate (^C, XON/XOFF, CR, LF, EOF)."""
    a, b = pair
    garbage = bytes(range(256)) + b"\r\n\n\r\x03\x04\x11\x13\x1a\x7f\xff\x00" * 4
    a.send(garbage)
    assert recv_exactly(b, len(garbage)) == garbage
    b.send(garbage[::-1])
    assert recv_exactly(a, len(garbage)) == garbage[::-1]


def test_recv_timeout_returns_empty_in_about_the_timeout(pair: tuple[Transport, Transport]) -> None:
    a, b = pair
    for end in (a, b):
        t0 = time.monotonic()
        assert end.recv(0.1) == b""
        assert 0.09 <= time.monotonic() - t0 < 0.5
        t0 = time.monotonic()
        assert end.recv(0.0) == b""
        assert time.monotonic() - t0 < 0.05


def test_stats_count_bytes_and_calls(pair: tuple[Transport, Transport]) -> None:
    a, b = pair
    sent0, recv0 = a.stats.bytes_sent, b.stats.bytes_received
    for _ in range(5):
        a.send(b"x" * 100)
    assert recv_exactly(b, 500) == b"x" * 500
    assert a.stats.bytes_sent - sent0 == 500
    assert b.stats.bytes_received - recv0 == 500
    assert a.stats.bytes_dropped == 0
    assert a.stats.send_calls >= 5


def test_close_is_idempotent_and_use_after_close_raises(pair: tuple[Transport, Transport]) -> None:
    a, b = pair
    for end in (a, b):
        end.close()
        end.close()
        assert end.closed
        with pytest.raises(LinkError, match="closed"):
            end.send(b"late")
        with pytest.raises(LinkError, match="closed"):
            end.recv(0.0)


@pytest.mark.parametrize("gone", ["a", "b"])
def test_peer_that_disappears_neither_crashes_nor_hangs(
    pair: tuple[Transport, Transport], gone: str, request: pytest.FixtureRequest
) -> None:
    a, b = pair
    name = request.node.callspec.params["pair"]
    expect_recv, expect_send = PEER_GONE[(name, gone)]
    leaver, survivor = (a, b) if gone == "a" else (b, a)
    leaver.close()
    t0 = time.monotonic()
    if expect_recv == "raises":
        with pytest.raises(LinkError):
            survivor.recv(1.0)
    else:
        assert survivor.recv(0.1) == b""
    dropped0 = survivor.stats.bytes_dropped
    if expect_send == "raises":
        with pytest.raises(LinkError):
            survivor.send(b"y" * 100)
    else:
        n = sum(survivor.send(b"y" * 100) for _ in range(3))
        if expect_send == "dropped":
            assert n == 0 and survivor.stats.bytes_dropped - dropped0 == 300
        else:
            assert n == 300
    assert time.monotonic() - t0 < 1.5


@pytest.mark.parametrize("name", ["memory", "pty-serial", "udp", "tcp"])
def test_fileno_becomes_readable_when_data_arrives(name: str) -> None:
    a, b = PAIRS[name]()
    with a, b:
        for src, dst in ((a, b), (b, a)):
            assert select.select([dst.fileno()], [], [], 0.0)[0] == []
            src.send(b"wake")
            assert select.select([dst.fileno()], [], [], 1.0)[0] == [dst.fileno()]
            assert recv_exactly(dst, 4) == b"wake"
            assert select.select([dst.fileno()], [], [], 0.0)[0] == []


# --- memory --------------------------------------------------------------------------------


def test_memory_full_buffer_drops_and_counts() -> None:
    a, b = MemoryTransport.pair(capacity_bytes=1000)
    with a, b:
        assert a.send(b"z" * 1500) == 1000
        assert a.stats.bytes_dropped == 500 and a.stats.bytes_sent == 1000
        assert a.send(b"more") == 0
        assert recv_exactly(b, 2000, timeout_s=0.2) == b"z" * 1000
        assert a.send(b"room again") == 10


def test_memory_reads_hand_over_what_was_written_in_order_whole_or_in_pieces() -> None:
    a, b = MemoryTransport.pair(capacity_bytes=10)
    with a, b:
        fd = b.fileno()
        assert a.send(b"abc") == 3 and a.send(bytearray(b"defg")) == 4 and a.send(b"hijkl") == 3
        assert b.recv(0.0, max_bytes=5) == b"abcde"  # (across the chunks written)
        assert select.select([fd], [], [], 0.0)[0] == [fd]  # the rest still waits
        assert a.send(b"xyz") == 3  # room again for what was read
        assert b.recv(0.0) == b"fghijxyz" and b.recv(0.0) == b""
        assert select.select([fd], [], [], 0.0)[0] == []


def test_memory_descriptor_asked_for_after_the_data_came_is_readable_until_it_is_read() -> None:
    a, b = MemoryTransport.pair()
    with a, b:
        a.send(b"early")  # before anyone asked for b's descriptor
        fd = b.fileno()
        assert select.select([fd], [], [], 0.0)[0] == [fd]
        assert b.recv(0.0) == b"early"
        assert select.select([fd], [], [], 0.0)[0] == []
        a.send(b"later")
        assert select.select([fd], [], [], 1.0)[0] == [fd] and b.fileno() == fd


def test_memory_rejects_a_nonpositive_capacity() -> None:
    with pytest.raises(ValueError, match="capacity"):
        MemoryTransport.pair(capacity_bytes=0)


def test_memory_survivor_still_reads_what_was_in_flight() -> None:
    a, b = MemoryTransport.pair()
    a.send(b"last words")
    a.close()
    assert b.peer_closed
    assert b.recv(0.1) == b"last words"
    b.close()


# --- pty and serial ------------------------------------------------------------------------


def test_pty_peer_can_close_and_reopen_the_path() -> None:
    with PtyTransport.create(921600) as fc:
        assert os.path.exists(fc.endpoint)
        for round_no in range(3):
            with serial.Serial(fc.endpoint, 921600, timeout=1.0) as port:
                msg = f"round {round_no}".encode()
                fc.send(msg)
                assert port.read(len(msg)) == msg
                port.write(b"ack")
                assert recv_exactly(fc, 3) == b"ack"
            assert fc.recv(0.05) == b""  # no EIO while no peer has the path open


def test_pty_path_serves_a_pymavlink_serial_connection() -> None:
    from pymavlink import mavutil

    with PtyTransport.create(921600) as fc:
        gcs = mavutil.mavlink_connection(fc.endpoint, baud=921600, source_system=255)
        try:
            enc = mavutil.mavlink.MAVLink(None, srcSystem=1)
            fc.send(enc.heartbeat_encode(2, 12, 0, 0, 0).pack(enc))
            hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=2.0)
            assert hb is not None and hb.get_srcSystem() == 1 and hb.autopilot == 12
            gcs.mav.heartbeat_send(6, 8, 0, 0, 0)
            parsed: list = []
            deadline = time.monotonic() + 2.0
            while not parsed and time.monotonic() < deadline:
                parsed = enc.parse_buffer(fc.recv(0.1)) or []
            assert [m.get_type() for m in parsed] == ["HEARTBEAT"] and parsed[0].get_srcSystem() == 255
        finally:
            gcs.close()


def test_pty_is_raw_for_a_peer_that_configures_nothing() -> None:
    """A program that just opens the path (no termios calls) sees no echo and no translation."""
    garbage = b"\r\n\x03\x04\x11\x13\x7f" + bytes(range(256))
    with PtyTransport.create() as fc:
        fd = os.open(fc.endpoint, os.O_RDWR | os.O_NOCTTY)
        try:
            fc.send(garbage)
            got = b""
            while len(got) < len(garbage) and select.select([fd], [], [], 1.0)[0]:
                got += os.read(fd, 4096)
            assert got == garbage
            os.write(fd, garbage)
            assert recv_exactly(fc, len(garbage)) == garbage
            assert fc.recv(0.05) == b""  # nothing echoed back
        finally:
            os.close(fd)


def test_pty_without_a_reader_drops_and_counts_once_the_kernel_buffer_is_full() -> None:
    with PtyTransport.create() as fc:
        t0 = time.monotonic()
        accepted = sum(fc.send(b"q" * 4096) for _ in range(64))  # 256 KiB, far beyond the buffer
        assert time.monotonic() - t0 < 1.0  # writes never block
        assert 0 < accepted < 64 * 4096
        assert fc.stats.bytes_dropped == 64 * 4096 - accepted
        fc.discard_pending()
        assert fc.send(b"after discard") == len(b"after discard")


def test_serial_open_of_a_missing_device_is_a_link_error() -> None:
    with pytest.raises(LinkError, match="/dev/does-not-exist"):
        SerialTransport("/dev/does-not-exist", 921600)


# --- UDP and TCP ---------------------------------------------------------------------------


def test_udp_server_drops_until_a_peer_has_spoken_then_follows_the_last_sender() -> None:
    with UdpTransport.server("127.0.0.1", 0) as srv:
        port = srv.local_address[1]
        assert srv.peer is None and srv.send(b"nobody") == 0 and srv.stats.bytes_dropped == 6
        with UdpTransport.client("127.0.0.1", port) as c1, UdpTransport.client("127.0.0.1", port) as c2:
            c1.send(b"one")
            assert srv.recv(1.0) == b"one"
            srv.send(b"to one")
            assert c1.recv(1.0) == b"to one"
            c2.send(b"two")
            assert srv.recv(1.0) == b"two"
            srv.send(b"to two")
            assert c2.recv(1.0) == b"to two" and c1.recv(0.05) == b""


def test_udp_datagram_larger_than_max_bytes_is_handed_out_in_pieces() -> None:
    a, b = _udp()
    with a, b:
        b.send(bytes(range(200)))
        assert a.recv(1.0, max_bytes=150) == bytes(range(150))
        assert a.recv(0.0, max_bytes=150) == bytes(range(150, 200))


def test_tcp_server_accepts_a_reconnecting_client() -> None:
    with TcpTransport.server("127.0.0.1", 0) as srv:
        port = int(srv.endpoint.rsplit(":", 1)[1])
        assert srv.send(b"no client") == 0 and srv.stats.bytes_dropped == 9
        for i in range(3):
            with TcpTransport.client("127.0.0.1", port) as cli:
                cli.send(b"hello %d" % i)
                assert recv_exactly(srv, 7) == b"hello %d" % i
                srv.send(b"ok")
                assert recv_exactly(cli, 2) == b"ok"
        assert srv.connections_accepted == 3


def test_tcp_connect_to_nobody_is_a_link_error() -> None:
    with TcpTransport.server("127.0.0.1", 0) as srv:
        port = int(srv.endpoint.rsplit(":", 1)[1])
    t0 = time.monotonic()
    with pytest.raises(LinkError, match="connect"):
        TcpTransport.client("127.0.0.1", port)
    assert time.monotonic() - t0 < 1.0


# --- UART wire time ------------------------------------------------------------------------


def test_uart_wire_time_is_ten_bits_a_byte() -> None:
    uart = UartModel(921600, clock=SimClock())
    assert uart.wire_time_s(51) == pytest.approx(553.385e-6, abs=1e-9)
    assert uart.wire_time_s(1) == pytest.approx(10 / 921600)


def test_uart_releases_exactly_the_bytes_whose_wire_time_elapsed() -> None:
    clock = SimClock()
    uart = UartModel(921600, tx_buffer_bytes=4096, clock=clock)
    frame = bytes(range(51))
    assert uart.write(frame) == 51
    assert uart.pump() == b""
    assert uart.next_release_s() == pytest.approx(10 / 921600)
    clock.advance_to(uart.wire_time_s(20) + 1e-9)
    first = uart.pump()
    assert first == frame[:20]
    clock.advance_to(uart.wire_time_s(51) - 1e-9)
    assert uart.pump() == frame[20:50]
    clock.advance_to(uart.wire_time_s(51))
    assert uart.pump() == frame[50:]
    assert uart.next_release_s() is None and uart.queued_bytes == 0


def test_uart_frames_queue_back_to_back_and_an_idle_line_starts_fresh() -> None:
    clock = SimClock()
    uart = UartModel(921600, clock=clock)
    uart.write(b"a" * 51)
    clock.advance_to(100e-6)
    uart.write(b"b" * 51)  # waits for the first frame to finish
    clock.advance_to(2 * uart.wire_time_s(51) - 1e-9)
    assert uart.pump() == b"a" * 51 + b"b" * 50
    clock.advance_to(1.0)
    assert uart.pump() == b"b"
    uart.write(b"c" * 51)  # idle line: starts now, not when the last frame ended
    assert uart.next_release_s() == pytest.approx(1.0 + 10 / 921600)
    clock.advance_to(1.0 + uart.wire_time_s(51))
    assert uart.pump() == b"c" * 51


def test_uart_full_tx_buffer_drops_and_counts_and_frees_as_bytes_leave() -> None:
    clock = SimClock()
    uart = UartModel(115200, tx_buffer_bytes=100, clock=clock)
    assert uart.write(b"x" * 150) == 100
    assert uart.bytes_dropped == 50
    clock.advance_to(uart.wire_time_s(60))
    assert uart.write(b"y" * 80) == 60  # 60 bytes have left the buffer, even before pump()
    assert uart.bytes_dropped == 70
    clock.advance_to(uart.wire_time_s(160))
    assert uart.pump() == b"x" * 100 + b"y" * 60


def test_uart_transport_in_simulated_time() -> None:
    clock = SimClock()
    fc, onboard = UartTransport.pair(921600, clock=clock, tx_buffer_bytes=64)
    with fc, onboard:
        assert fc.send(b"m" * 51) == 51
        assert onboard.recv(0.0) == b""  # nothing has left the wire at t = 0
        clock.advance_to(fc.uart.wire_time_s(51))
        assert onboard.recv(0.0) == b"m" * 51
        assert fc.send(b"n" * 100) == 64 and fc.stats.bytes_dropped == 36


def test_uart_transport_wraps_any_transport_and_is_pumped_on_demand() -> None:
    clock = SimClock()
    a_mem, b = MemoryTransport.pair()
    a = UartTransport(a_mem, 921600, clock)
    with a, b:
        a.send(b"p" * 51)
        clock.advance_to(a.next_release_s() or 0.0)
        assert a.pump() == 1
        clock.advance_to(a.uart.wire_time_s(51))
        assert a.pump() == 50
        assert b.recv(0.0) == b"p" * 51


def test_uart_transport_in_wall_time_takes_the_wire_time() -> None:
    fc, onboard = UartTransport.pair(9600)  # 51 bytes: 53.1 ms
    with fc, onboard:
        t0 = time.monotonic()
        fc.send(b"w" * 51)
        got = recv_exactly(onboard, 51)
        elapsed = time.monotonic() - t0
        assert got == b"w" * 51
        assert 0.052 <= elapsed < 0.2


@pytest.mark.parametrize("kwargs", [{"baud": 0}, {"baud": 9600, "tx_buffer_bytes": 0}])
def test_uart_rejects_bad_settings(kwargs: dict[str, int]) -> None:
    with pytest.raises(ValueError):
        UartModel(**kwargs)


# --- endpoint specs ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("pty", EndpointSpec("pty", baud=921600)),
        ("pty:230400", EndpointSpec("pty", baud=230400)),
        ("serial:/dev/ttyUSB0:921600", EndpointSpec("serial", device="/dev/ttyUSB0", baud=921600)),
        ("serial:/dev/ttyTHS2", EndpointSpec("serial", device="/dev/ttyTHS2", baud=921600)),
        ("udp:127.0.0.1:14550", EndpointSpec("udp", host="127.0.0.1", port=14550)),
        ("udpout:localhost:14540", EndpointSpec("udpout", host="localhost", port=14540)),
        ("tcp:0.0.0.0:5760", EndpointSpec("tcp", host="0.0.0.0", port=5760)),
        ("tcpout:127.0.0.1:5760", EndpointSpec("tcpout", host="127.0.0.1", port=5760)),
        ("memory", EndpointSpec("memory", name="default")),
        ("memory:run1", EndpointSpec("memory", name="run1")),
    ],
)
def test_parse_endpoint_accepts_every_documented_spec(spec: str, expected: EndpointSpec) -> None:
    assert parse_endpoint(spec) == expected
    assert parse_endpoint(str(expected)) == expected


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("", "empty"),
        ("bluetooth:aa", "unknown link kind"),
        ("udp:127.0.0.1", "HOST:PORT"),
        ("tcp:127.0.0.1:70000", "HOST:PORT"),
        ("udpout::14550", "HOST:PORT"),
        ("pty:fast", "baud"),
        ("serial:", "DEVICE"),
    ],
)
def test_parse_endpoint_explains_a_bad_spec(spec: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_endpoint(spec)


def test_open_link_pairs_named_memory_ends_and_wraps_a_uart() -> None:
    onboard = open_link("memory:t1", "onboard")
    fc = open_link("memory:t1", "fc")
    with fc, onboard:
        fc.send(b"hi")
        assert onboard.recv(1.0) == b"hi"
    half = open_link("memory:t2", "fc")
    with pytest.raises(ValueError, match="already open"):
        open_link("memory:t2", "fc")
    open_link("memory:t2", "onboard").close()
    half.close()
    clock = SimClock()
    with open_link("pty:115200", "fc", clock=clock, uart_baud=115200) as pty:
        assert isinstance(pty, UartTransport) and isinstance(pty.inner, PtyTransport)
        with open_link(f"serial:{pty.endpoint}:115200", "onboard") as port:
            pty.send(b"abc")
            assert port.recv(0.05) == b""
            clock.advance_to(pty.uart.wire_time_s(3))
            pty.pump()
            assert recv_exactly(port, 3) == b"abc"


def test_open_link_refuses_bad_roles_and_an_onboard_pty() -> None:
    with pytest.raises(ValueError, match="role"):
        open_link("memory", "ground")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="serial:/dev/pts"):
        open_link("pty", "onboard")


@pytest.mark.parametrize("spin_s", [0.0, 0.05])
def test_wait_readable_sees_bytes_from_another_process_and_times_out(spin_s):
    from hil.link.transport import wait_readable

    master, slave = os.openpty()
    try:
        assert not wait_readable([master], 0.02, spin_s)  # nothing written: False after the timeout
        pid = os.fork()
        if pid == 0:  # another process writes 10 ms later, while the parent spins or sleeps
            time.sleep(0.01)
            os.write(slave, b"tick")
            os._exit(0)
        assert wait_readable([master], 2.0, spin_s)
        assert os.read(master, 16) == b"tick"
        os.waitpid(pid, 0)
    finally:
        os.close(master)
        os.close(slave)
