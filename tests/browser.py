"""A headless Chromium driven over the DevTools protocol, for the tests of the view's page: open a URL,
evaluate JavaScript in it, take a screenshot. Skips the test when no chromium is installed."""

from __future__ import annotations

import asyncio
import base64
import itertools
import json
import shutil
import subprocess
import time
import urllib.request
from pathlib import Path
from typing import Any

import pytest

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--window-size=1280,1000"]


def chromium_path() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


class Browser:
    """One headless browser with one page."""

    def __init__(self, profile_dir: Path, timeout_s: float = 60.0) -> None:
        exe = chromium_path()
        if exe is None:
            pytest.skip("no chromium installed (apt-get install chromium)")
        aiohttp = pytest.importorskip("aiohttp")
        argv = [exe, *FLAGS, "--remote-debugging-port=0", f"--user-data-dir={profile_dir}", "about:blank"]
        self.proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = profile_dir / "DevToolsActivePort"
        deadline = time.monotonic() + timeout_s
        while not port_file.is_file() or not port_file.read_text().strip():
            if time.monotonic() > deadline or self.proc.poll() is not None:
                self.close()
                raise RuntimeError("chromium did not start")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            page = next(t for t in json.load(r) if t["type"] == "page")
        self.loop = asyncio.new_event_loop()
        self._ids = itertools.count(1)

        async def connect() -> Any:
            self.session = aiohttp.ClientSession()
            return await self.session.ws_connect(page["webSocketDebuggerUrl"], max_msg_size=0)

        self.ws = self.loop.run_until_complete(connect())

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """One DevTools command and its result."""
        msg_id = next(self._ids)

        async def go() -> dict[str, Any]:
            await self.ws.send_str(json.dumps({"id": msg_id, "method": method, "params": params}))
            while True:
                msg = json.loads((await self.ws.receive(timeout=60)).data)
                if msg.get("id") == msg_id:
                    if "error" in msg:
                        raise RuntimeError(f"{method}: {msg['error']}")
                    return msg["result"]

        return self.loop.run_until_complete(go())

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def eval(self, expression: str) -> Any:
        """The value of ``expression`` in the page (JSON-able)."""
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def wait_for(self, expression: str, timeout_s: float = 30.0) -> Any:
        """Poll ``expression`` until it is truthy; its value."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                value = self.eval(expression)
            except RuntimeError:
                value = None
            if value:
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"never true in {timeout_s:g} s: {expression}")
            time.sleep(0.1)

    def screenshot(self, path: Path) -> None:
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))

    def close(self) -> None:
        if getattr(self, "ws", None) is not None:
            async def shut() -> None:
                await self.ws.close()
                await self.session.close()

            self.loop.run_until_complete(shut())
            self.loop.close()
            self.ws = None
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
