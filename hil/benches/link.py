"""Link figures: round-trip time of a 51-byte frame (one SET_ATTITUDE_TARGET) over each transport."""

from __future__ import annotations

from collections.abc import Callable, Iterable

from hil.benches import BenchRow, time_per_call
from hil.link import (
    LinkError,
    MemoryTransport,
    PtyTransport,
    SerialTransport,
    TcpTransport,
    Transport,
    UdpTransport,
)

FRAME = bytes(range(51))


def _pty() -> tuple[Transport, Transport]:
    a = PtyTransport.create()
    return a, SerialTransport(a.endpoint, a.baud)


def _udp() -> tuple[Transport, Transport]:
    a = UdpTransport.server("127.0.0.1", 0)
    b = UdpTransport.client("127.0.0.1", a.local_address[1])
    b.send(b"\x00")
    a.recv(1.0)
    return a, b


def _tcp() -> tuple[Transport, Transport]:
    a = TcpTransport.server("127.0.0.1", 0)
    return a, TcpTransport.client("127.0.0.1", int(a.endpoint.rsplit(":", 1)[1]))


PAIRS: dict[str, Callable[[], tuple[Transport, Transport]]] = {
    "memory": MemoryTransport.pair,
    "pty": _pty,
    "udp": _udp,
    "tcp": _tcp,
}


def _read(t: Transport, n: int) -> bytes:
    got = b""
    while len(got) < n:
        chunk = t.recv(1.0, n - len(got))
        if not chunk:
            raise LinkError(f"{t.endpoint}: frame lost during the bench")
        got += chunk
    return got


def collect(quick: bool) -> Iterable[BenchRow]:
    min_time_s = 0.1 if quick else 0.5
    for name, make in PAIRS.items():
        a, b = make()
        with a, b:

            def round_trip(a: Transport = a, b: Transport = b) -> None:
                a.send(FRAME)
                b.send(_read(b, len(FRAME)))
                _read(a, len(FRAME))

            rtt_s = time_per_call(round_trip, min_time_s=min_time_s)
        yield BenchRow(f"link.{name}.rtt_51B", rtt_s * 1e6, "us", "send 51 B, echo back, read; one thread")
