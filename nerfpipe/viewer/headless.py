"""Headless Chromium driving the viewer page, for tests, benchmarks and screenshots.

Chromium is started with its DevTools protocol on a local port and driven over its WebSocket
(``websockets``, which viser already depends on): no browser download, no WebDriver. Every host but
this machine is unresolvable to it (``--host-resolver-rules``) and every request it makes is logged
(:attr:`Chromium.requests`), so a page that needs the internet shows as such. WebGL runs on
SwiftShader (software), as on a machine without a GPU.

The viser client exposes its scene for tests (``window.__viserSceneTree``, ``window.__viserMutable``);
:data:`FRUSTUMS_JS` and friends read them.
"""

import base64
import json
import os
import re
import shutil
import subprocess
import threading
import time
import urllib.request
from pathlib import Path

FRUSTUMS_JS = """(() => { const t = window.__viserSceneTree; if (!t) return -1;
  return Object.values(t.getState()).filter(n => n && n.message && n.message.type === 'CameraFrustumMessage'
    && n.message.name.startsWith('/cameras/')).length; })()"""
"""Number of camera frustums under ``/cameras`` in the page's scene (-1 before the client is up)."""

NODES_JS = """(() => { const t = window.__viserSceneTree; if (!t) return null;
  return Object.values(t.getState()).filter(n => n && n.message).map(n => n.message.name); })()"""
"""Names of the scene nodes in the page."""

BACKGROUND_JS = """(() => { const m = window.__viserMutable; const u = m && m.backgroundMaterial && m.backgroundMaterial.uniforms;
  if (!u || !u.enabled.value || !u.colorMap.value || !u.colorMap.value.image) return null;
  return [u.colorMap.value.image.width, u.colorMap.value.image.height]; })()"""
"""``[width, height]`` of the live render shown in the page, or null."""

WATCH_BACKGROUND_JS = """(() => { window.__bgLog = []; let last = null;
  setInterval(() => { const m = window.__viserMutable; const u = m && m.backgroundMaterial && m.backgroundMaterial.uniforms;
    const t = u && u.enabled.value ? u.colorMap.value : null;
    if (t && t.image && t !== last) { last = t; window.__bgLog.push([Date.now(), t.image.width, t.image.height]); } }, 5);
  return true; })()"""
"""Starts logging ``[ms since the epoch, width, height]`` each time the page's live render changes (``window.__bgLog``)."""

WATCH_MESSAGES_JS = """(() => { const m = window.__viserMutable; window.__cameraSent = []; window.__imageReceived = [];
  const send = m.sendMessage;
  m.sendMessage = (msg) => { if (msg.type === 'ViewerCameraMessage') window.__cameraSent.push(Date.now()); return send(msg); };
  const queue = m.messageQueue, push = queue.push.bind(queue);
  queue.push = (...items) => { for (const it of items) if (it.type === 'BackgroundImageMessage') window.__imageReceived.push(Date.now()); return push(...items); };
  return true; })()"""
"""Starts logging, in ms since the epoch, each camera the page sends (``window.__cameraSent``) and each live
render it receives (``window.__imageReceived``, when it enters the page's message queue, before it is decoded
and drawn): with :data:`WATCH_BACKGROUND_JS`, a move's latency splits into the page's part before the
camera leaves, the server's (and the socket's), and the page's part after the image came. (It wraps the
client's ``sendMessage`` and its queue's ``push``: a reconnect replaces the former.)"""


def find_chromium() -> "str | None":
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


class Chromium:
    """One headless Chromium with one page, driven over the DevTools protocol."""

    def __init__(self, profile: Path, width: int = 1200, height: int = 800, exe: "str | None" = None, timeout: float = 30.0) -> None:
        from websockets.sync.client import connect

        exe = exe or find_chromium()
        if exe is None:
            raise RuntimeError("no chromium executable (apt-get install chromium)")
        args = [exe, "--headless", "--no-sandbox", "--remote-debugging-port=0", f"--user-data-dir={profile}",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader", f"--window-size={width},{height}",
                "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--disable-quic", "--hide-scrollbars", "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE localhost , EXCLUDE 127.0.0.1",
                "about:blank"]  # fmt: skip
        self.process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env={**os.environ, "LANG": "C"})
        self.requests: "list[str]" = []
        """URL of every request the page made."""
        self._id = 0
        try:
            port = self._devtools_port(timeout)
            pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=timeout).read())
            page = next(p for p in pages if p["type"] == "page")
            # no keepalive pings: on a loaded machine a late pong would close a connection that is fine
            self._ws = connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=timeout, ping_interval=None)
            self.call("Network.enable")
            self.call("Page.enable")
            self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        except Exception:
            self.close()
            raise

    def _devtools_port(self, timeout: float) -> int:
        deadline = time.monotonic() + timeout
        for line in self.process.stderr:
            m = re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line)
            if m:  # keep draining its log, or a full pipe would stall it
                threading.Thread(target=lambda: [None for _ in self.process.stderr], daemon=True).start()
                return int(m.group(1))
            if time.monotonic() > deadline:
                break
        raise RuntimeError("chromium did not start its DevTools server")

    def call(self, method: str, **params) -> dict:
        """Send one DevTools command and return its result (events met on the way are recorded)."""
        self._id += 1
        self._ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self._ws.recv(timeout=60))
            if msg.get("method") == "Network.requestWillBeSent":
                self.requests.append(msg["params"]["request"]["url"])
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg["result"]

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (JSON-able)."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return result.get("result", {}).get("value")

    def wait_for(self, expression: str, until=lambda v: bool(v), timeout: float = 30.0, every: float = 0.05):
        """Poll ``expression`` until ``until(value)``; returns the value (raises TimeoutError with the last one)."""
        deadline = time.monotonic() + timeout
        while True:
            value = self.evaluate(expression)
            if until(value):
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"{expression[:60]}... stayed {value!r} for {timeout} s")
            time.sleep(every)

    def screenshot(self, path: Path) -> Path:
        data = self.call("Page.captureScreenshot", format="png")["data"]
        Path(path).write_bytes(base64.b64decode(data))
        return Path(path)

    def outside_requests(self) -> "list[str]":
        """Requests to anything but this machine (``data:``/``blob:`` URLs are in the page)."""
        local = re.compile(r"^(data:|blob:|about:|(https?|wss?)://(localhost|127\.0\.0\.1)(:\d+)?/)")
        return [u for u in self.requests if not local.match(u)]

    def close(self) -> None:
        try:
            if hasattr(self, "_ws"):
                self._ws.close()
        finally:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)


__all__ = ["BACKGROUND_JS", "FRUSTUMS_JS", "NODES_JS", "WATCH_BACKGROUND_JS", "WATCH_MESSAGES_JS", "Chromium", "find_chromium"]
