"""A headless Chromium driven over the Chrome DevTools Protocol, for the browser test of the view.

Debian's ``chromium`` package only (``scripts/setup_chromium.sh``), never a browser download. It is
started with a fresh profile and no background networking (its own update, sync and component
fetches would otherwise try to leave the machine), in a process group of its own that
:meth:`Chromium.close` ends. The protocol runs over a websocket to 127.0.0.1 (websocket-client).
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from typing import Any

CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-default-apps", "--disable-extensions", "--mute-audio",
    # WebGL without a GPU: SwiftShader, which recent Chromium enables only when asked.
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0",
)


def chromium_path() -> str | None:
    """The system Chromium, or None."""
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    return None


class CdpError(RuntimeError):
    """The browser answered a DevTools call with an error, or did not answer."""


class Chromium:
    """One headless Chromium with one page; ``call`` sends a DevTools command to that page."""

    def __init__(self, executable: str, *, width: int = 1024, height: int = 768,
                 timeout: float = 60.0) -> None:
        import websocket  # websocket-client

        self.profile = tempfile.mkdtemp(prefix="redarm_chromium_")
        # Its log goes to a file: a pipe nobody reads would stall the browser once full.
        self.log_path = os.path.join(self.profile, "chromium.log")
        self._log = open(self.log_path, "wb")  # noqa: SIM115 - closed in close()
        self.proc = subprocess.Popen(
            [executable, *CHROMIUM_FLAGS, f"--user-data-dir={self.profile}",
             f"--window-size={width},{height}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT,
            start_new_session=True)
        self.events: list[dict[str, Any]] = []
        self._id = 0
        self._timeout = timeout
        try:
            port = self._devtools_port(timeout)
            page = self._page_target(port, timeout)
            # No Origin header: Chromium refuses DevTools websockets from unknown origins.
            self.ws = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=timeout,
                                                  suppress_origin=True)
            self.call("Page.enable")
            self.call("Network.enable")
            self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                      mobile=False)
        except BaseException:
            self.close()
            raise

    def _devtools_port(self, timeout: float) -> int:
        path = os.path.join(self.profile, "DevToolsActivePort")
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise CdpError(f"chromium exited with {self.proc.returncode}: {self.log_tail()}")
            try:
                with open(path, encoding="ascii") as fh:
                    lines = fh.read().split("\n")
                if len(lines) >= 2 and lines[0].strip().isdigit():
                    return int(lines[0])
            except OSError:
                pass
            time.sleep(0.05)
        raise CdpError(f"chromium did not open its DevTools port within {timeout} s")

    @staticmethod
    def _page_target(port: int, timeout: float) -> dict[str, Any]:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                pages = [t for t in json.load(r) if t.get("type") == "page"]
            if pages:
                return pages[0]
            time.sleep(0.1)
        raise CdpError("chromium has no page target")

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """Send one DevTools command and return its result (events seen meanwhile go to ``events``)."""
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise CdpError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self.events.append(msg)

    def wait_event(self, method: str, timeout: float) -> dict[str, Any]:
        """Wait for the next event ``method`` (those already seen count) and return it."""
        for e in self.events:
            if e.get("method") == method:
                self.events.remove(e)
                return e
        self.ws.settimeout(timeout)
        end = time.monotonic() + timeout
        try:
            while time.monotonic() < end:
                msg = json.loads(self.ws.recv())
                if msg.get("method") == method:
                    return msg
                self.events.append(msg)
        finally:
            self.ws.settimeout(self._timeout)
        raise CdpError(f"no {method} within {timeout} s")

    def navigate(self, url: str, timeout: float = 60.0) -> None:
        """Open ``url`` in the page and wait for its load event."""
        self.events = [e for e in self.events if e.get("method") != "Page.loadEventFired"]
        self.call("Page.navigate", url=url)
        self.wait_event("Page.loadEventFired", timeout)

    def screenshot(self) -> bytes:
        """PNG bytes of the page's viewport."""
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def drag(self, x0: float, y0: float, x1: float, y1: float, steps: int = 15,
             pause_s: float = 0.04) -> None:
        """Press the left button at (x0, y0), move in ``steps`` to (x1, y1), release (CSS pixels)."""
        self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x0, y=y0)
        time.sleep(pause_s)
        self.call("Input.dispatchMouseEvent", type="mousePressed", x=x0, y=y0, button="left", buttons=1,
                  clickCount=1)
        for i in range(1, steps + 1):
            f = i / steps
            self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x0 + f * (x1 - x0),
                      y=y0 + f * (y1 - y0), button="left", buttons=1)
            time.sleep(pause_s)
        self.call("Input.dispatchMouseEvent", type="mouseReleased", x=x1, y=y1, button="left", buttons=0,
                  clickCount=1)

    def requested_urls(self) -> list[str]:
        """Every URL the page requested so far (Network.requestWillBeSent)."""
        return [e["params"]["request"]["url"] for e in self.events
                if e.get("method") == "Network.requestWillBeSent"]

    def log_tail(self, n: int = 2000) -> str:
        """The last ``n`` characters of the browser's own log."""
        try:
            with open(self.log_path, "rb") as fh:
                return fh.read().decode(errors="replace")[-n:]
        except OSError:
            return ""

    def close(self) -> None:
        """End the browser and every process it started; remove the profile."""
        ws = getattr(self, "ws", None)
        if ws is not None:
            try:
                ws.send(json.dumps({"id": self._id + 1, "method": "Browser.close"}))
                ws.close()
            except Exception:  # noqa: BLE001 - the browser may already be gone
                pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            pass
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)  # renderer/zygote helpers share the group
        except ProcessLookupError:
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass
        self._log.close()
        shutil.rmtree(self.profile, ignore_errors=True)
