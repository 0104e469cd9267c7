"""Screenshots of the viewer in headless Chromium (for the browser test and the README image).

Chromium is driven through the DevTools protocol (a websocket; the ``websockets`` package comes with
viser): open the page, wait until the scene has drawn and stopped changing, capture a PNG. WebGL
runs on SwiftShader, Chromium's CPU renderer, so no GPU or display is needed.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mapkit.errors import MapkitError

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
#: Flags that give headless Chromium a software WebGL context (SwiftShader through ANGLE).
CHROMIUM_FLAGS = (
    "--headless=new",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--hide-scrollbars",
    "--mute-audio",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-extensions",
    "--disable-background-networking",
)
# viser shows a "Software WebGL rendering detected" notice on SwiftShader; the script closes it.
_DISMISS_JS = """
(() => { let n = 0;
  for (const el of document.querySelectorAll('[role="alert"]')) {
    if (el.textContent.includes('WebGL')) { const b = el.querySelector('button'); if (b) b.click();
      el.style.visibility = 'hidden'; n += 1; } }
  return n; })()
"""


class BrowserError(MapkitError):
    """Headless Chromium is missing or did not produce a screenshot."""


def find_chromium() -> str | None:
    """Path of a Chromium executable ($MAPKIT_CHROMIUM, else chromium / google-chrome on PATH), or None."""
    env = os.environ.get("MAPKIT_CHROMIUM")
    if env:
        return env if Path(env).is_file() else shutil.which(env)
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


class _Cdp:
    """A minimal DevTools-protocol session over one page's websocket."""

    def __init__(self, ws_url: str) -> None:
        from websockets.sync.client import connect

        self._ws = connect(ws_url, max_size=None, open_timeout=15)
        self._id = 0

    def call(self, method: str, timeout: float = 30.0, **params: Any) -> dict[str, Any]:
        self._id += 1
        my_id = self._id
        self._ws.send(json.dumps({"id": my_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            try:
                msg = json.loads(self._ws.recv(timeout=max(0.1, deadline - time.monotonic())))
            except TimeoutError:
                raise BrowserError(f"Chromium did not answer {method} within {timeout:.0f} s (a heavy scene "
                                   f"rendered in software, or a loaded machine); try again or show fewer layers") from None
            if msg.get("id") == my_id:
                if "error" in msg:
                    raise BrowserError(f"Chromium refused {method}: {msg['error'].get('message')}")
                return msg.get("result", {})

    def close(self) -> None:
        self._ws.close()


def screenshot(
    url: str,
    path: str | Path,
    *,
    width: int = 1400,
    height: int = 900,
    timeout: float = 90.0,
    min_wait: float = 2.0,
    ready: Callable[[np.ndarray], bool] | None = None,
    settle: bool = True,
    chromium: str | None = None,
) -> Path:
    """Open `url` in headless Chromium and save a PNG of the page at `path`.

    Waits at least `min_wait` seconds, then captures every half second until `ready` (a test on
    the uint8 (height, width, 3) image; default: always) holds for two identical captures in a row
    (the scene has arrived and stopped changing; with ``settle=False`` the first capture for which
    `ready` holds is kept), or raises :class:`BrowserError` after `timeout`
    (the last capture is then saved at `path` for inspection).
    """
    exe = chromium or find_chromium()
    if exe is None:
        raise BrowserError("no Chromium found; install Debian's `chromium` (apt-get install chromium) or set MAPKIT_CHROMIUM")
    out = Path(path)
    tmp = Path(tempfile.mkdtemp(prefix="mapkit-chromium-"))
    proc, log = _launch_chromium(exe, tmp, width, height)
    cdp = None
    try:
        deadline = time.monotonic() + timeout
        cdp = _connect(exe, proc, tmp, deadline)
        cdp.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        cdp.call("Page.navigate", url=url)
        return _capture_when_ready(cdp, url, out, deadline=deadline, timeout=timeout, min_wait=min_wait, ready=ready,
                                   settle=settle)
    finally:
        _close_chromium(cdp, proc, log, tmp)


def _launch_chromium(exe: str, tmp: Path, width: int, height: int) -> tuple[subprocess.Popen, Any]:
    """Start headless Chromium on about:blank with its profile and log in ``tmp`` → (process, open log file)."""
    args = [exe, *CHROMIUM_FLAGS, f"--window-size={width},{height}", f"--user-data-dir={tmp / 'profile'}",
            "--remote-debugging-port=0", "about:blank"]
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        args.insert(1, "--no-sandbox")  # Chromium's sandbox refuses to run as root (CI containers)
    log = open(tmp / "chromium.log", "wb")  # noqa: SIM115 - the browser's output until _close_chromium
    proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    return proc, log


def _connect(exe: str, proc: subprocess.Popen, tmp: Path, deadline: float) -> _Cdp:
    """A DevTools connection to Chromium's first page, once its debugging port is up (by ``deadline``)."""
    port_file = tmp / "profile" / "DevToolsActivePort"
    while not (port_file.is_file() and port_file.read_text().strip()):
        if proc.poll() is not None or time.monotonic() > deadline:
            raise BrowserError(f"Chromium did not start ({exe}); see {tmp / 'chromium.log'}")
        time.sleep(0.1)
    port = int(port_file.read_text().split()[0])
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as resp:
        pages = [t for t in json.load(resp) if t.get("type") == "page"]
    if not pages:
        raise BrowserError("Chromium opened no page")
    return _Cdp(pages[0]["webSocketDebuggerUrl"])


def _capture_when_ready(cdp: _Cdp, url: str, out: Path, *, deadline: float, timeout: float, min_wait: float,
                        ready: Callable[[np.ndarray], bool] | None, settle: bool) -> Path:
    """Capture every half second after ``min_wait`` until ``ready`` holds on a settled capture; save it at ``out``."""
    from PIL import Image

    started = time.monotonic()
    previous: np.ndarray | None = None
    while True:
        time.sleep(0.5)
        if time.monotonic() > deadline:
            kept = ""
            if previous is not None:  # keep the last capture: it shows what went wrong
                out.parent.mkdir(parents=True, exist_ok=True)
                Image.fromarray(previous).save(out)
                kept = f"; the last capture is in {out}"
            raise BrowserError(f"the page at {url} did not settle into a ready scene within {timeout:.0f} s{kept}")
        if time.monotonic() - started < min_wait:
            continue
        cdp.call("Runtime.evaluate", expression=_DISMISS_JS)
        shot = cdp.call("Page.captureScreenshot", format="png", timeout=60.0)
        png = base64.b64decode(shot["data"])
        image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
        settled = not settle or (previous is not None and np.array_equal(image, previous))
        if (ready is None or ready(image)) and settled:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(png)
            return out
        previous = image


def _close_chromium(cdp: _Cdp | None, proc: subprocess.Popen, log: Any, tmp: Path) -> None:
    """Close the browser (politely, then by force), the log, and remove ``tmp``."""
    if cdp is not None:
        with contextlib.suppress(Exception):  # the browser may already be gone
            cdp.call("Browser.close", timeout=5.0)
        cdp.close()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
    log.close()
    shutil.rmtree(tmp, ignore_errors=True)
