"""The view's web server on loopback (stdlib only): the page, the scene, a stream of frames as
server-sent events while a run flies, and a finished run's frames for the page's time slider.

One thread samples the source `rate_hz` times a second (the emulator's loop does nothing for the view)
into the run's log of frames; each browser connected to ``/stream`` gets that log from the run's first
frame on (a page opened late, or reloaded, shows the whole run), then every frame as it is sampled.
`finish(run_dir)` ends the stream (the page then fetches ``/replay.json`` and replays the run with a
slider); `replay(run_dir)` serves a finished run from the start.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any, Protocol

from hil.view.replay import ReplayError, load_replay

#: frames a second sent while a run flies
DEFAULT_RATE_HZ = 25.0
#: frames a run's log keeps (two hours at the default rate; a scenario lasts an hour at most): beyond,
#: the oldest tenth goes (a standalone FC's view runs for as long as it is left)
MAX_LOG_FRAMES = 180_000


class Source(Protocol):
    def scene(self) -> dict[str, Any]: ...
    def frame(self) -> dict[str, Any]: ...


def page_html() -> str:
    """The page: one self-contained file (inline script and style, nothing from the network)."""
    return resources.files("hil.view").joinpath("page.html").read_text(encoding="utf-8")


class ViewServer:
    """Serves the view on ``host:port`` (port 0: a free one) from a thread; see the module docstring."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, rate_hz: float = DEFAULT_RATE_HZ) -> None:
        self.rate_hz = rate_hz
        self._cond = threading.Condition()
        #: the live run's frames from its first, in order, each as the stream sends it (encoded once, by
        #: the sampler: a page that connects late costs a join, not an encoding of the whole run)
        self._frames: list[bytes] = []
        self._latest: dict[str, Any] | None = None
        self._first_k = 0  # the log's place of self._frames[0] (more than 0 once the oldest went)
        self._run = 0  # runs shown live so far: a page replaying one moves on to the next live run
        self._source: Source | None = None
        self._replay: dict[str, Any] | None = None
        self._replay_dir: Path | None = None
        self._done = False
        self._holding = False
        self._closed = False
        self._sampler: threading.Thread | None = None
        self.frames_sampled = 0
        self._page = page_html().encode()
        self._httpd = ThreadingHTTPServer((host, port), self._handler())
        self._httpd.daemon_threads = True
        self._thread = threading.Thread(target=self._httpd.serve_forever, name="hil-view", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        host, port = self._httpd.server_address[:2]
        return f"http://{host}:{port}/"

    # --- what is shown -----------------------------------------------------------------------------
    def live(self, source: Source) -> None:
        """Stream ``source``'s frames from now on."""
        with self._cond:
            self._source, self._done, self._replay, self._replay_dir = source, False, None, None
            self._frames, self._first_k, self._latest, self._holding = [], 0, None, False
            self._run += 1
            self._cond.notify_all()  # (a page's stream of the run before ends now)
        self._sampler = threading.Thread(target=self._sample, args=(source,), name="hil-view-sampler",
                                         daemon=True)
        self._sampler.start()

    def hold(self) -> None:
        """Stop sampling the source (its emulator is about to close); the last frame stays."""
        sampler, self._sampler = self._sampler, None
        with self._cond:
            self._holding = True
        if sampler is not None:
            sampler.join(timeout=2.0)

    def finish(self, run_dir: str | Path | None) -> None:
        """The run is over: stop sampling, end the stream; the page then replays ``run_dir`` (if given)."""
        self.hold()
        with self._cond:
            self._done = True
            self._replay_dir = None if run_dir is None else Path(run_dir)
            self._replay = None
            self._cond.notify_all()

    def replay(self, run_dir: str | Path) -> dict[str, Any]:
        """Serve the finished run in ``run_dir`` (ReplayError when it is none); returns what is served."""
        data = load_replay(run_dir)
        with self._cond:
            self._source, self._done, self._replay, self._replay_dir = None, True, data, Path(run_dir)
            self._cond.notify_all()
        return data

    def close(self) -> None:
        with self._cond:
            self._closed = self._done = True
            self._cond.notify_all()
        self._httpd.shutdown()
        self._httpd.server_close()

    # --- sampling ----------------------------------------------------------------------------------
    def _sample(self, source: Source) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        while True:
            with self._cond:
                if self._done or self._holding or self._source is not source:
                    return
            try:
                frame = source.frame()
            except Exception as exc:  # a frame that cannot be read is shown, never fatal to the run
                frame = {"error": f"{type(exc).__name__}: {exc}"}
            with self._cond:
                if self._source is not source:  # (the next run started meanwhile)
                    return
                frame["k"] = self._first_k + len(self._frames)  # its place in the run's log
                self._frames.append(b"data: " + json.dumps(frame, separators=(",", ":")).encode() + b"\n\n")
                self._latest = frame
                if len(self._frames) > MAX_LOG_FRAMES:
                    cut = MAX_LOG_FRAMES // 10
                    del self._frames[:cut]
                    self._first_k += cut
                self.frames_sampled += 1
                self._cond.notify_all()
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))

    def _state(self) -> dict[str, Any]:
        with self._cond:
            mode = "replay" if self._done else "live"
            source, run = self._source, self._run
        if mode == "live" and source is not None:
            return {"mode": mode, "scene": source.scene(), "run": run}
        data = self._replay_data()
        return {"mode": "replay" if data else "waiting", "scene": data["scene"] if data else None, "run": run}

    def _replay_data(self) -> dict[str, Any] | None:
        with self._cond:
            if self._replay is not None or self._replay_dir is None:
                return self._replay
            run_dir = self._replay_dir
        try:
            data = load_replay(run_dir)
        except ReplayError as exc:
            data = {"scene": {"title": str(exc)}, "frames": []}
        with self._cond:
            self._replay = data
        return data

    def _stream(self, write: Any) -> None:
        """The frames of the run live when the page asked, from its first (what came before the page
        connected too), ended by ``done`` when that run is over, also when the next one has already
        started (a stream never goes on with another run's frames)."""
        next_k = 0
        with self._cond:
            run, frames = self._run, self._frames
        while True:
            with self._cond:
                self._cond.wait_for(lambda k=next_k: self._first_k + len(frames) > k or self._done
                                    or self._run != run, timeout=1.0)
                over = self._done or self._run != run
                start = max(0, next_k - self._first_k)
                batch = frames[start:] if self._run == run else []
                next_k = self._first_k + start + len(batch)
            if batch:
                write(b"".join(batch))
            elif over:
                write(b"event: done\ndata: {}\n\n")
                return
            else:
                write(b": keep-alive\n\n")

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        view = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, format: str, *args: Any) -> None:  # quiet: the run's output is the log
                pass

            def _send(self, body: bytes, kind: str, status: int = HTTPStatus.OK) -> None:
                self.send_response(status)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def do_GET(self) -> None:
                path = self.path.split("?")[0]
                if path == "/":
                    self._send(view._page, "text/html; charset=utf-8")
                elif path == "/state.json":
                    self._send(json.dumps(view._state()).encode(), "application/json")
                elif path == "/replay.json":
                    self._send(json.dumps(view._replay_data() or {"frames": []}).encode(), "application/json")
                elif path == "/frame.json":
                    with view._cond:
                        frame = view._latest
                    self._send(json.dumps(frame).encode(), "application/json")
                elif path == "/stream":
                    self.send_response(HTTPStatus.OK)
                    self.send_header("Content-Type", "text/event-stream")
                    self.send_header("Cache-Control", "no-store")
                    self.end_headers()

                    def write(data: bytes) -> None:
                        self.wfile.write(data)
                        self.wfile.flush()

                    with contextlib.suppress(BrokenPipeError, ConnectionResetError):
                        view._stream(write)
                else:
                    self._send(b"not found", "text/plain", HTTPStatus.NOT_FOUND)

        return Handler


def serve_until_stopped(view: ViewServer) -> None:
    """Keep serving ``view`` until Ctrl-C or SIGTERM, then close it."""
    import signal

    stop = threading.Event()
    old = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        while not stop.wait(0.2):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, old)
        view.close()
