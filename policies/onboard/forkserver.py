"""The onboard program started warm: a server process that has imported the program once and forks one
fresh copy of itself per run (one kept forked ahead, waiting for its run's arguments), so that a run
pays a hand-over (milliseconds) instead of an interpreter start and the imports of numpy, pymavlink and
the pilots (about 0.3-0.5 s).

Each child runs ``python -m policies.onboard`` as a cold start does (what its ``__main__`` runs,
`policies.onboard.cli.main_and_leave`, on the arguments and the stderr it is given, stdin and stdout on
/dev/null), in a copy of the server's memory as it was after the imports: the server never runs a
program itself, so no state passes from one run to the next. The server forks, reaps and reports;
`ForkServer.spawn` returns a `ForkedProcess`, which a harness watches, signals (through a pidfd: never a
recycled pid) and waits on as it would a `subprocess.Popen`: a killed or stopped child is killed or
stopped as a cold one is.

The protocol, on AF_UNIX SOCK_SEQPACKET sockets (one message per send, descriptors beside it):
    control socket (one per server; harness processes forked after it started share it): the request
        ``{"args": [...], "preload": "pilot name"|null,
        "cpus": [...]|null}`` (the CPUs the child keeps to: the asking harness's) with two descriptors:
        the run's channel and the child's stderr;
    run channel (one per child): the server's ``{"pid": N}`` with the child's pidfd, then
        ``{"exit": code, "cpu_s": s}`` (negative code: the signal that ended it; its CPU time, user
        + system) once it has been reaped; the channel closes after it.
A child whose run channel the harness closes (the harness dropped it, or exited) is ended: continued,
then killed through its pidfd, since a stopped child cannot notice its links closing. The server ends
when its control socket closes (its harnesses exited), ending the children still running the same way.

    python -m policies.onboard.forkserver FD     # FD: the control socket, inherited
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import importlib
import json
import math
import os
import select
import selectors
import signal
import socket
import subprocess
import sys
import threading
import traceback
from typing import IO, Any

from hil.link.memory import MemoryTransport
from policies.onboard.cli import main_and_leave, parser
from policies.onboard.command_links import COMMAND_LINKS
from policies.onboard.pilots import PILOTS
from policies.onboard.program import EventLog, OnboardProgram, ProgramConfig, warm_kernels
from policies.vehicle import DEFAULT_VEHICLE, load_vehicle

#: the program the children run (as ``python -m MODULE``)
MODULE = "policies.onboard"
#: the modules the server imports before it forks (the pilots: see `_preload`)
PRELOAD = ("numpy", "serial", "hil.link.serial_port", "policies.onboard.cli")
MAX_MESSAGE_BYTES = 1 << 16
#: the server's messages on a run's channel ({"pid": N}, {"exit": code}) are far shorter (polled each tick)
CHANNEL_MESSAGE_BYTES = 256
#: the first spawn waits for the server to import everything (s); later ones take milliseconds
START_TIMEOUT_S = 60.0


def available() -> bool:
    """Whether this platform can run the server (fork, pidfds, SCM_RIGHTS: Linux 5.3 or later)."""
    return hasattr(os, "pidfd_open") and hasattr(signal, "pidfd_send_signal") and hasattr(socket, "send_fds")


# --- the server ------------------------------------------------------------------------------------
_preloaded: set[str] = set()


def _preload(pilot: str | None) -> None:
    """Import the program and, if named, a pilot's module (a learned pilot's brings onnxruntime), once."""
    key = pilot or ""
    if key in _preloaded:
        return
    _preloaded.add(key)
    for name in PRELOAD:
        importlib.import_module(name)
    if not key:  # what the program makes on its first use of them: its parser, vehicle files, kernels
        parser()
        load_vehicle(DEFAULT_VEHICLE)
        warm_kernels()
        _build_programs()
    if pilot:
        with contextlib.suppress(Exception):  # an unknown pilot is the program's to refuse, cold or warm
            PILOTS.load(pilot)
    gc.collect()  # (no gc.freeze(): the children collect as a cold program does, so they run as fast)


def _build_programs() -> None:
    """Build (and close) a program on each command-link protocol over memory links, so that what a
    program builds the same in every run is made here once, before the forks: its kernels' compiled
    forms for its arguments' types (`policies.compiling.Kernel.entry`), its codec's tables."""
    for protocol in COMMAND_LINKS:
        (command, _), (mocap, _) = MemoryTransport.pair(), MemoryTransport.pair()
        OnboardProgram(command, mocap, ProgramConfig(fc_protocol=protocol), events=EventLog()).close()


def serve(control_fd: int) -> int:
    """Serve fork requests on ``control_fd`` until it closes; returns the exit code (0)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is the harness's to handle, not ours
    _preload(None)
    return _Server(socket.socket(fileno=control_fd)).run()


class _Server:
    """The server's loop: requests on the control socket, children's exits on their pidfds, and one spare
    child forked ahead (at the start, and when a run's child has ended), waiting for its run's arguments:
    the fork is then off the next run's start-up."""

    def __init__(self, control: socket.socket) -> None:
        self.control = control
        self.sel = selectors.DefaultSelector()
        self.sel.register(control, selectors.EVENT_READ, None)
        self.children: dict[int, tuple[int, socket.socket]] = {}  # pidfd -> (pid, run channel)
        self.spare: tuple[int, socket.socket] | None = None  # (pid, the socket it waits on)

    def run(self) -> int:
        self.spare = self._fork_spare()
        while True:
            for key, _ in self.sel.select():
                if isinstance(key.data, int):  # a child's pidfd: it has exited
                    if key.fd in self.children:
                        self._reap(key.fd)
                    continue
                if key.data is not None:  # a run's channel: readable only when its harness closed it
                    self._on_channel(key.data[1])
                    continue
                try:
                    data, fds, _, _ = socket.recv_fds(self.control, MAX_MESSAGE_BYTES, 2)
                except OSError:
                    data, fds = b"", []
                if not data:
                    self._end_children()
                    return 0
                self._start(data, fds)

    def _on_channel(self, pidfd: int) -> None:
        """A run's channel turned readable: the harness closed it (the child is ended) or, against the
        protocol, wrote to it (read and dropped)."""
        if pidfd not in self.children:  # (reaped in the same round)
            return
        _, chan = self.children[pidfd]
        try:
            data = chan.recv(CHANNEL_MESSAGE_BYTES, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self.sel.unregister(chan)
            _end(pidfd)  # its pidfd reports the exit: reaped then

    def _end_children(self) -> None:
        """End every child still running (continued, then killed) and reap it."""
        for pidfd, (pid, chan) in list(self.children.items()):
            _end(pidfd)
            with contextlib.suppress(ChildProcessError):
                os.waitpid(pid, 0)
            chan.close()
            os.close(pidfd)
        self.children.clear()

    def _reap(self, pidfd: int) -> None:
        pid, chan = self.children.pop(pidfd)
        self.sel.unregister(pidfd)
        with contextlib.suppress(KeyError, ValueError):
            self.sel.unregister(chan)
        _, status, usage = os.wait4(pid, 0)
        # its exit code, and the CPU time it used in all (user + system, s): a run's own cost, which
        # wall time on a shared machine does not tell
        message = {"exit": os.waitstatus_to_exitcode(status), "cpu_s": usage.ru_utime + usage.ru_stime}
        with contextlib.suppress(OSError):
            chan.send(json.dumps(message).encode())
        chan.close()
        os.close(pidfd)
        if self.spare is None:  # the next run's child, forked now that this one is over (not while it
            self.spare = self._fork_spare()  # starts: the fork would take the CPU it starts on)

    def _start(self, data: bytes, fds: list[int]) -> None:
        """Hand a request to the spare child (or a new one if there is none), report its pid and pidfd on
        the run's channel."""
        if len(fds) != 2:
            for fd in fds:
                os.close(fd)
            return
        chan, stderr_fd = socket.socket(fileno=fds[0]), fds[1]
        try:
            request = json.loads(data)
            args = [str(a) for a in request["args"]]
            preload = request.get("preload")
            cpus = request.get("cpus")
        except (ValueError, KeyError, TypeError) as exc:
            with contextlib.suppress(OSError):
                chan.send(json.dumps({"error": f"bad request: {exc}"}).encode())
            chan.close()
            os.close(stderr_fd)
            return
        pid = self._hand_over(json.dumps({"args": args, "cpus": cpus}).encode(), stderr_fd)
        os.close(stderr_fd)
        pidfd = os.pidfd_open(pid)
        self.children[pidfd] = (pid, chan)
        self.sel.register(pidfd, selectors.EVENT_READ, pid)
        try:
            socket.send_fds(chan, [json.dumps({"pid": pid}).encode()], [pidfd])
            self.sel.register(chan, selectors.EVENT_READ, ("channel", pidfd))
        except OSError:  # the harness has gone: the child goes too
            _end(pidfd)
        if preload:
            _preload(str(preload))  # (a pilot's first run imports it itself; the next spares have it)

    def _hand_over(self, args: bytes, stderr_fd: int) -> int:
        """The pid of the child now running ``args``: the spare, or a new child if there is none (runs at
        once) or the spare has gone."""
        spare, self.spare = self.spare, None
        if spare is not None:
            pid, sock = spare
            try:
                socket.send_fds(sock, [args], [stderr_fd])
                return pid
            except OSError:  # it died waiting: reaped, and a new child runs the request
                with contextlib.suppress(ChildProcessError):
                    os.waitpid(pid, 0)
            finally:
                sock.close()
        spare = self._fork_spare()
        pid, sock = spare
        socket.send_fds(sock, [args], [stderr_fd])
        sock.close()
        return pid

    def _fork_spare(self) -> tuple[int, socket.socket]:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                ours.close()
                self.sel.close()
                self.control.close()
                for pidfd, (_, chan) in self.children.items():
                    chan.close()
                    os.close(pidfd)
                try:
                    data, fds, _, _ = socket.recv_fds(theirs, MAX_MESSAGE_BYTES, 1)  # waits for its run
                except OSError:
                    data, fds = b"", []
                theirs.close()
                run = json.loads(data) if data and len(fds) == 1 else None
                if run is not None and run.get("cpus") and hasattr(os, "sched_setaffinity"):
                    with contextlib.suppress(OSError, ValueError, TypeError):
                        os.sched_setaffinity(0, run["cpus"])  # the CPUs of the harness that asked
                code = _child(run["args"], fds[0]) if run is not None else 0
            finally:
                os._exit(code)
        theirs.close()
        return pid, ours


def _end(pidfd: int) -> None:
    """Continue, then kill, the process of ``pidfd`` (a stopped process would never see its links close)."""
    for sig in (signal.SIGCONT, signal.SIGKILL):
        with contextlib.suppress(ProcessLookupError):
            signal.pidfd_send_signal(pidfd, sig)


def _child(args: list[str], stderr_fd: int) -> int:
    """Run the program in this fresh child, as ``python -m MODULE ARGS`` would; its exit code (when it
    did not leave by itself)."""
    # its own process group, as a program the harness starts cold: a Ctrl-C at the terminal is the
    # harness's to handle (a suite lets the runs in flight finish), never a death mid-run
    os.setpgid(0, 0)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # (the server ignores it; Python's own)
    devnull = os.open(os.devnull, os.O_RDWR)
    os.dup2(devnull, 0)
    os.dup2(devnull, 1)
    os.dup2(stderr_fd, 2)
    os.close(devnull)
    os.close(stderr_fd)
    sys.argv = [MODULE, *args]
    try:
        # what the module's __main__ runs, called here: finding and loading that file again in each
        # child (runpy) would be ~2 ms of its start
        main_and_leave(args)  # (leaves by os._exit)
    except SystemExit as exc:
        code = exc.code
        if code is None or isinstance(code, int):
            return code or 0
        print(code, file=sys.stderr)
        return 1
    except BaseException:  # the child's last word, as the interpreter would print it
        traceback.print_exc()
        return 1
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
    return 0


# --- the client ------------------------------------------------------------------------------------
class ForkServerError(OSError):
    """The server could not start a program (it did not start, or it has gone)."""


class ForkedProcess:
    """A program the server forked, with `subprocess.Popen`'s ``pid``, ``returncode``, ``poll``,
    ``wait``, ``send_signal``, ``terminate`` and ``kill``; signals go through its pidfd."""

    def __init__(self, pid: int, pidfd: int, chan: socket.socket) -> None:
        self.pid = pid
        self.returncode: int | None = None
        self.cpu_s: float | None = None  # its CPU time in all (user + system, s), once it has exited
        self._pidfd: int | None = pidfd
        self._chan = chan
        # asked once a tick in a run whether a message has come: a poll object answers without the
        # exception a non-blocking read raises when none has
        self._poller = select.poll()
        self._poller.register(chan, select.POLLIN)

    def poll(self) -> int | None:
        """The exit code once the server has reaped the program, else None (no read while nothing
        waits on the channel)."""
        if self.returncode is None and self._poller.poll(0):
            try:
                data = self._chan.recv(CHANNEL_MESSAGE_BYTES, socket.MSG_DONTWAIT)
            except BlockingIOError:
                return None
            except OSError:
                data = b""
            self._on_message(data)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """Wait for the exit code; `subprocess.TimeoutExpired` after ``timeout`` (s)."""
        if self.returncode is None:
            ready, _, _ = select.select([self._chan], [], [], timeout)
            if not ready:
                raise subprocess.TimeoutExpired(MODULE, timeout or 0.0)
            self.poll()
            if self.returncode is None:  # (not a message yet: a spurious wake-up)
                return self.wait(timeout)
        return self.returncode  # type: ignore[return-value]

    def send_signal(self, sig: int) -> None:
        if self.poll() is None and self._pidfd is not None:
            with contextlib.suppress(ProcessLookupError):
                signal.pidfd_send_signal(self._pidfd, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        """Continue it (were it stopped), then kill it."""
        if self.poll() is None and self._pidfd is not None:
            _end(self._pidfd)

    def _on_message(self, data: bytes) -> None:
        msg: dict[str, Any] = {}
        with contextlib.suppress(ValueError):
            msg = json.loads(data) if data else {}
        if isinstance(msg.get("exit"), int):
            self.returncode = msg["exit"]
            cpu = msg.get("cpu_s")  # (a figure that is not a time is no figure)
            ok = isinstance(cpu, int | float) and not isinstance(cpu, bool) and 0.0 <= cpu < math.inf
            self.cpu_s = float(cpu) if ok else None
        elif not data:  # the server has gone without a word: end the program, as a harness would
            if self._pidfd is not None:
                _end(self._pidfd)
            self.returncode = -signal.SIGKILL
        else:
            return
        self._release()

    def _release(self) -> None:
        if self._pidfd is not None:
            os.close(self._pidfd)
            self._pidfd = None
        with contextlib.suppress(KeyError, ValueError):
            self._poller.unregister(self._chan)
        self._chan.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            if self._pidfd is not None:
                self._release()


class ForkServer:
    """A server process (started here, importing in the background) and the control socket to it."""

    def __init__(self, env: dict[str, str] | None = None) -> None:
        if not available():
            raise ForkServerError("warm starts need Linux 5.3 or later (fork, pidfds)")
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", __name__, str(theirs.fileno())],
                pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, env=env,
            )
        finally:
            theirs.close()
        self._sock = ours
        self._lock = threading.Lock()
        self.owner_pid = os.getpid()

    def spawn(self, args: list[str], stderr: IO[bytes], preload: str | None = None) -> ForkedProcess:
        """Start ``python -m policies.onboard ARGS`` warm, its stderr on ``stderr``; ``preload`` names a
        pilot whose module the server imports first (once). ForkServerError when the server cannot."""
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            with self._lock:
                cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
                request = json.dumps({"args": args, "preload": preload, "cpus": cpus}).encode()
                socket.send_fds(self._sock, [request], [theirs.fileno(), stderr.fileno()])
            theirs.close()
            ours.settimeout(START_TIMEOUT_S)
            data, fds, _, _ = socket.recv_fds(ours, CHANNEL_MESSAGE_BYTES, 1)
            ours.settimeout(None)
        except OSError as exc:
            ours.close()
            raise ForkServerError(f"onboard fork server: {exc}") from exc
        finally:
            theirs.close()
        msg: dict[str, Any] = {}
        with contextlib.suppress(ValueError):
            msg = json.loads(data) if data else {}
        if not isinstance(msg.get("pid"), int) or len(fds) != 1:
            for fd in fds:
                os.close(fd)
            ours.close()
            raise ForkServerError(f"onboard fork server: {msg.get('error', 'no answer (it has exited)')}")
        return ForkedProcess(msg["pid"], fds[0], ours)

    def alive(self) -> bool:
        """Whether the server is still there (asked of its process by any process that shares it)."""
        if self.owner_pid == os.getpid():
            return self.proc.poll() is None
        try:
            os.kill(self.proc.pid, 0)
        except OSError:
            return False
        return True

    def close(self) -> None:
        """End the server and the children it still runs; only the process that started it can."""
        if self.owner_pid != os.getpid():
            return
        self._sock.close()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(2.0)
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


_shared: ForkServer | None = None


def shared(env: dict[str, str] | None = None) -> ForkServer | None:
    """This process's server, started on first use (None where warm starts are not available). Processes
    forked from this one after it started use it too (a suite's workers: one server imports for all);
    each request carries its CPUs, which the program keeps to."""
    global _shared
    if not available():
        return None
    if _shared is None or not _shared.alive():
        _shared = ForkServer(env)
        atexit.register(_shared.close)
    return _shared


def close_shared() -> None:
    """End this process's server (and what it still runs), if it started one."""
    global _shared
    if _shared is not None:
        _shared.close()
        _shared = None


if __name__ == "__main__":
    sys.exit(serve(int(sys.argv[1])))
