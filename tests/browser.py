"""A real headless Chromium, driven over the DevTools protocol, for testing report.html.

Debian's ``chromium`` (installed by ``tools/browser_setup.sh`` from ``make test``) runs with a
fresh profile and no network; a page is loaded and everything that went wrong is collected:
console errors, uncaught exceptions, failed or refused requests. Then a screenshot and a PDF.
"""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--remote-debugging-port=0",
    "--window-size=1200,900",
]


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@dataclass
class PageLoad:
    """What loading a page gave."""

    errors: list[str] = field(default_factory=list)  # console errors, exceptions, failed requests
    requests: list[str] = field(default_factory=list)  # every URL the page asked for
    screenshot_png: bytes = b""
    pdf: bytes = b""
    title: str = ""
    images: int = 0  # <img> elements
    images_broken: int = 0  # <img> elements that did not decode


class _Session:
    def __init__(self, ws_url: str) -> None:
        import websocket

        self._ws = websocket.create_connection(ws_url, timeout=60, suppress_origin=True)
        self._id = 0
        self.events: list[dict[str, Any]] = []

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        self._id += 1
        self._ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self._ws.recv())
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return dict(msg.get("result", {}))
            self.events.append(msg)

    def wait_for(self, event: str, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not any(e.get("method") == event for e in self.events):
            if time.monotonic() > deadline:
                raise TimeoutError(f"no {event} in {timeout_s} s")
            self.events.append(json.loads(self._ws.recv()))

    def close(self) -> None:
        self._ws.close()


def load(url: str, *, settle_s: float = 0.5) -> PageLoad:
    """Open ``url`` in headless Chromium and report what happened."""
    exe = chromium()
    if exe is None:
        raise FileNotFoundError("chromium")
    profile = Path(tempfile.mkdtemp(prefix="geoortho-chromium-"))
    proc = subprocess.Popen(
        [exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + 60
        while not (port_file.is_file() and port_file.read_text().strip()):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("chromium did not open its DevTools port")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            pages = [t for t in json.load(r) if t.get("type") == "page"]
        s = _Session(pages[0]["webSocketDebuggerUrl"])
        try:
            return _load(s, url, settle_s)
        finally:
            s.close()
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
        shutil.rmtree(profile, ignore_errors=True)


def _load(s: _Session, url: str, settle_s: float) -> PageLoad:
    for domain in ("Page", "Runtime", "Log", "Network"):
        s.call(f"{domain}.enable")
    s.call("Page.navigate", url=url)
    s.wait_for("Page.loadEventFired")
    time.sleep(settle_s)
    out = PageLoad()
    out.title = s.call("Runtime.evaluate", expression="document.title", returnByValue=True)["result"]["value"]
    counts = s.call(
        "Runtime.evaluate",
        expression="JSON.stringify([document.images.length,"
        " Array.from(document.images).filter(i => !(i.complete && i.naturalWidth > 0)).length])",
        returnByValue=True,
    )["result"]["value"]
    out.images, out.images_broken = json.loads(counts)
    metrics = s.call("Page.getLayoutMetrics")["cssContentSize"]
    shot = s.call(
        "Page.captureScreenshot",
        format="png",
        captureBeyondViewport=True,
        clip={"x": 0, "y": 0, "width": 1200, "height": min(float(metrics["height"]), 4000.0), "scale": 1},
    )
    out.screenshot_png = base64.b64decode(shot["data"])
    out.pdf = base64.b64decode(s.call("Page.printToPDF", printBackground=True)["data"])
    for e in s.events:
        method, p = e.get("method"), e.get("params", {})
        if method == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            out.errors.append("console: " + " ".join(str(a.get("value", a.get("description"))) for a in p["args"]))
        elif method == "Runtime.exceptionThrown":
            out.errors.append("exception: " + str(p.get("exceptionDetails", {}).get("text")))
        elif method == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
            out.errors.append(f"log: {p['entry'].get('text')} {p['entry'].get('url', '')}")
        elif method == "Network.loadingFailed":
            out.errors.append(f"request failed: {p.get('errorText')} ({p.get('type')})")
        elif method == "Network.requestWillBeSent":
            out.requests.append(p["request"]["url"])
        elif method == "Network.responseReceived" and p["response"].get("status", 200) >= 400:
            out.errors.append(f"HTTP {p['response']['status']}: {p['response']['url']}")
    return out
