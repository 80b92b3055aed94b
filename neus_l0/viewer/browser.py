"""Headless Chromium over the DevTools protocol: open a page, wait for a text, take a
screenshot, evaluate JavaScript, and log every request the page made.

Used by ``neus-l0 view RUN --screenshot FILE`` (the README's picture) and by the tests of
the page and of the videos. Chromium runs with a fresh profile, no background networking,
and a host resolver that resolves nothing but the loopback, so a page that asks for an
outside address is logged (`Shot.outside`) and never reaches it.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import json
import re
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from urllib.parse import urlsplit

from neus_l0.errors import NeusL0Error

#: Executables tried in order.
CHROMIUM = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")

FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run",
         "--disable-default-apps", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1, EXCLUDE localhost",
         "--remote-debugging-port=0", "--autoplay-policy=no-user-gesture-required")


#: JavaScript that removes viser's notices (e.g. "Software WebGL rendering detected").
HIDE_NOTICES = ("document.querySelectorAll('.mantine-Notification-root')"
                ".forEach(e => e.remove()); true")


@dataclasses.dataclass
class Shot:
    """What a page did in the browser.

    Attributes:
        path: the screenshot written (None without one).
        text: the page's visible text (``document.body.innerText``).
        requests: every URL the page requested; outside: those not on the loopback.
        value: what the `evaluate` expression returned.
    """

    path: Path | None
    text: str
    requests: list[str]
    outside: list[str]
    value: object = None


def find_chromium() -> str | None:
    """The path of a Chromium executable on PATH, or None."""
    for name in CHROMIUM:
        path = shutil.which(name)
        if path:
            return path
    return None


def on_loopback(url: str) -> bool:
    """Whether a requested URL stays on this machine (loopback, data:, blob:, about:)."""
    parts = urlsplit(url)
    if parts.scheme in ("data", "blob", "about", "file", "chrome", "devtools"):
        return True
    return (parts.hostname or "") in ("127.0.0.1", "localhost", "::1")


class _Cdp:
    """A DevTools session on one page target, over a synchronous websocket."""

    def __init__(self, ws_url: str) -> None:
        from websockets.sync.client import connect

        self.ws = connect(ws_url, max_size=2**28)
        self.next_id = 0
        self.requests: list[str] = []

    def call(self, method: str, timeout: float = 30.0, **params) -> dict:
        """Send a command and wait for its result (recording requests meanwhile)."""
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        end = time.monotonic() + timeout
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.1, end - time.monotonic())))
            if msg.get("method") == "Network.requestWillBeSent":
                self.requests.append(msg["params"]["request"]["url"][:200])
            elif msg.get("method") == "Network.webSocketCreated":
                self.requests.append(msg["params"]["url"])
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise NeusL0Error(f"chromium: {method}: {msg['error'].get('message')}")
                return msg.get("result", {})

    def evaluate(self, expression: str, timeout: float = 30.0):
        """The value of a JavaScript expression (promises awaited)."""
        res = self.call("Runtime.evaluate", timeout=timeout, expression=expression,
                        awaitPromise=True, returnByValue=True)
        return res.get("result", {}).get("value")


@contextlib.contextmanager
def chromium(size: tuple[int, int] = (1280, 800), timeout: float = 30.0):
    """A headless Chromium with one blank page: yields a `_Cdp` session on it.

    Raises:
        NeusL0Error: no Chromium on PATH, or it does not start.
    """
    exe = find_chromium()
    if exe is None:
        raise NeusL0Error("chromium: not found on PATH (apt-get install -y chromium)")
    # Chromium's helper processes can still write the profile while it is removed: a
    # leftover file in our own temporary folder must not fail the page's capture
    with tempfile.TemporaryDirectory(prefix="neus-l0-chromium-",
                                     ignore_cleanup_errors=True) as profile:
        proc = subprocess.Popen([exe, *FLAGS, f"--user-data-dir={profile}",
                                 f"--window-size={size[0]},{size[1]}", "about:blank"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            port = _devtools_port(proc, timeout)
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
                pages = [t for t in json.load(r) if t.get("type") == "page"]
            cdp = _Cdp(pages[0]["webSocketDebuggerUrl"])
            try:
                cdp.call("Network.enable")
                cdp.call("Page.enable")
                yield cdp
            finally:
                cdp.ws.close()
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()


def _devtools_port(proc: subprocess.Popen, timeout: float) -> int:
    """The DevTools port Chromium prints on stderr at start."""
    end = time.monotonic() + timeout
    lines = []
    while time.monotonic() < end:
        line = proc.stderr.readline()
        if not line and proc.poll() is not None:
            break
        lines.append(line.strip())
        m = re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line)
        if m:
            return int(m.group(1))
    tail = " | ".join(x for x in lines[-3:] if x)
    raise NeusL0Error(f"chromium: did not start ({tail or 'no output'})")


def open_page(url: str, screenshot: str | Path | None = None, wait_text: str | None = None,
              evaluate: str | None = None, settle: float = 2.0,
              timeout: float = 30.0) -> Shot:
    """Open `url` in headless Chromium, wait for `wait_text` on the page (then `settle`
    seconds more), evaluate `evaluate`, and save a PNG screenshot to `screenshot`.

    Raises:
        NeusL0Error: no Chromium, or `wait_text` did not show within `timeout` seconds.
    """
    with chromium(timeout=timeout) as cdp:
        cdp.call("Page.navigate", url=url)
        end = time.monotonic() + timeout
        text = ""
        while True:
            text = cdp.evaluate("document.body ? document.body.innerText : ''") or ""
            if wait_text is None or wait_text in text or time.monotonic() > end:
                break
            time.sleep(0.25)
        if wait_text is not None and wait_text not in text:
            raise NeusL0Error(f"{url}: {wait_text!r} did not show within {timeout:.0f} s")
        time.sleep(settle)
        value = cdp.evaluate(evaluate, timeout) if evaluate else None
        path = None
        if screenshot is not None:
            data = cdp.call("Page.captureScreenshot", format="png")["data"]
            path = Path(screenshot)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(base64.b64decode(data))
        text = cdp.evaluate("document.body ? document.body.innerText : ''") or text
        reqs = list(cdp.requests)
    return Shot(path, text, reqs, [u for u in reqs if not on_loopback(u)], value)


def screenshot_run(run_dir: str | Path, out: str | Path, resolution: int = 128) -> Shot:
    """Serve a run's page on a free loopback port and save its screenshot to `out`.

    Raises:
        NeusL0Error: no Chromium, the page did not show the run's PSNR, or it asked for
            an address off the loopback.
    """
    from neus_l0.viewer.serve import open_run_page

    page, _state = open_run_page(run_dir, "127.0.0.1", 0, resolution)
    try:
        shot = open_page(f"http://127.0.0.1:{page.port}/", out, wait_text="last PSNR",
                         evaluate=HIDE_NOTICES, settle=4.0)
    finally:
        page.close()
    if shot.outside:
        raise NeusL0Error(f"{out}: the page asked for {shot.outside[0]} (off the loopback)")
    return shot
