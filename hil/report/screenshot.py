"""Screenshot a report page with headless Chromium: ``python -m hil.report.screenshot report.html out.png``.

Chromium is found on PATH (chromium, chromium-browser, google-chrome); on Debian:
``apt-get install -y chromium``. Networking features are switched off: the page needs none.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_browser() -> str | None:
    """Path of a Chromium-family browser, or None."""
    for name in BROWSERS:
        found = shutil.which(name)
        if found:
            return found
    return None


def screenshot(
    html_path: str | Path,
    png_path: str | Path,
    width: int = 1280,
    height: int = 2000,
    timeout_s: float = 60.0,
) -> Path:
    """Render ``html_path`` to ``png_path`` (width x height pixels); raises RuntimeError on failure."""
    browser = find_browser()
    if browser is None:
        raise RuntimeError(
            f"no Chromium found on PATH (tried {', '.join(BROWSERS)}); "
            "install one, e.g. apt-get install -y chromium"
        )
    page = Path(html_path).resolve()
    if not page.is_file():
        raise RuntimeError(f"{html_path}: no such file")
    png = Path(png_path).resolve()
    png.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="hil-chromium-") as profile:
        cmd = [
            browser,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
            f"--user-data-dir={profile}",
            f"--screenshot={png}",
            f"--window-size={width},{height}",
            page.as_uri(),
        ]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
        except subprocess.TimeoutExpired as exc:
            raise RuntimeError(f"{browser} did not finish within {timeout_s:.0f} s") from exc
    if proc.returncode != 0 or not png.is_file():
        raise RuntimeError(f"{browser} failed (exit {proc.returncode}): {proc.stderr.strip()[-500:]}")
    return png


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m hil.report.screenshot", description=__doc__.splitlines()[0]
    )
    parser.add_argument("html", help="the report.html to render")
    parser.add_argument("png", help="where to write the screenshot")
    parser.add_argument("--width", type=int, default=1280, help="window width (px)")
    parser.add_argument("--height", type=int, default=2000, help="window height (px)")
    args = parser.parse_args(argv)
    try:
        out = screenshot(args.html, args.png, args.width, args.height)
    except RuntimeError as exc:
        print(f"screenshot: {exc}", file=sys.stderr)
        return 1
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
