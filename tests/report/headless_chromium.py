"""Load a page in Debian's headless `chromium` without network access and report what rendered.

The browser is driven through the DevTools protocol over `--remote-debugging-pipe` (file
descriptors 3 and 4, NUL-separated JSON), so no websocket library is needed. Every name
resolves to nothing and every proxied request goes to a closed port: a page that needs the
network cannot get it. Besides the DOM facts a caller asks for, the report lists the page's
console errors, uncaught exceptions and every request that left the machine's files.
"""

from __future__ import annotations

import base64
import contextlib
import fcntl
import json
import os
import select
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: Chromium refuses every network path: no DNS, a proxy on a closed port, no background fetches.
OFFLINE_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--host-resolver-rules=MAP * ~NOTFOUND",
    "--proxy-server=http://127.0.0.1:9",
    "--allow-file-access-from-files",
)
LOCAL_SCHEMES = ("file:", "data:", "about:", "blob:", "chrome:", "devtools:")


def chromium_path() -> str | None:
    return shutil.which("chromium")


@dataclass
class PageReport:
    """What a page did while it loaded: `facts` is the value of the caller's probe."""

    facts: Any = None
    console_errors: list[str] = field(default_factory=list)
    exceptions: list[str] = field(default_factory=list)
    network_requests: list[str] = field(default_factory=list)


class _Pipe:
    """One DevTools connection: commands out on fd 3, replies and events in on fd 4."""

    def __init__(self, process: subprocess.Popen, to_browser: int, from_browser: int) -> None:
        self.process, self.to_browser, self.from_browser = process, to_browser, from_browser
        self.buffer = b""
        self.next_id = 0
        self.events: list[dict[str, Any]] = []

    def send(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        self.next_id += 1
        message: dict[str, Any] = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self.to_browser, json.dumps(message).encode() + b"\0")
        while True:
            reply = self._receive(timeout=30.0)
            if reply is None:
                raise TimeoutError(f"chromium did not answer {method}")
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)

    def pump(self, seconds: float) -> None:
        """Collect events for `seconds`."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            event = self._receive(timeout=left)
            if event is not None:
                self.events.append(event)

    def _receive(self, timeout: float) -> dict | None:
        deadline = time.monotonic() + timeout
        while b"\0" not in self.buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.from_browser], [], [], left)[0]:
                return None
            chunk = os.read(self.from_browser, 1 << 16)
            if not chunk:
                raise RuntimeError(f"chromium exited (code {self.process.poll()})")
            self.buffer += chunk
        message, self.buffer = self.buffer.split(b"\0", 1)
        return json.loads(message)


def load_offline(
    url: str,
    probe: str,
    ready: str,
    *,
    timeout: float = 60.0,
    settle: float = 1.0,
    screenshot: Path | None = None,
    viewport: tuple[int, int] | None = None,
) -> PageReport:
    """Open `url`, wait until the JavaScript expression `ready` is true (or `timeout`), let the
    page settle, and return the value of the expression `probe` with the page's errors; with
    `screenshot`, the page as the probe left it is saved there as PNG. `viewport`: the window's
    (width, height) in CSS pixels, instead of chromium's default."""
    chromium = chromium_path()
    if chromium is None:
        raise FileNotFoundError("chromium is not installed")
    # Chromium's helper processes may still write the profile as it is removed.
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as profile:
        to_browser_read, to_browser = os.pipe()
        from_browser, from_browser_write = os.pipe()
        # bash (dash cannot name fds above 9) puts the browser's pipe ends on fds 3 and 4, where
        # --remote-debugging-pipe wants them; moved above 9 first, so that neither redirection
        # overwrites the other.
        to_browser_read, from_browser_write = (
            _above_nine(to_browser_read),
            _above_nine(from_browser_write),
        )
        command = [
            "bash",
            "-c",
            f'exec "$0" "$@" 3<&{to_browser_read} 4>&{from_browser_write}',
            chromium,
            *OFFLINE_FLAGS,
            f"--user-data-dir={profile}",
            "--remote-debugging-pipe",
            "about:blank",
        ]
        process = subprocess.Popen(
            command,
            pass_fds=(to_browser_read, from_browser_write),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,  # its own process group: the helpers go with it
        )
        os.close(to_browser_read)
        os.close(from_browser_write)
        try:
            pipe = _Pipe(process, to_browser, from_browser)
            return _inspect(pipe, url, probe, ready, timeout, settle, screenshot, viewport)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            os.close(to_browser)
            os.close(from_browser)


def _above_nine(fd: int) -> int:
    moved = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
    os.close(fd)
    return moved


def _inspect(
    pipe: _Pipe,
    url: str,
    probe: str,
    ready: str,
    timeout: float,
    settle: float,
    screenshot: Path | None = None,
    viewport: tuple[int, int] | None = None,
) -> PageReport:
    target = pipe.send("Target.createTarget", {"url": "about:blank"})["targetId"]
    session = pipe.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
    for domain in ("Runtime", "Log", "Network", "Page"):
        pipe.send(f"{domain}.enable", session=session)
    if viewport is not None:
        width, height = viewport
        metrics = {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False}
        pipe.send("Emulation.setDeviceMetricsOverride", metrics, session=session)
    pipe.send("Page.navigate", {"url": url}, session=session)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not _evaluate(pipe, session, ready):
        pipe.pump(0.2)
    pipe.pump(settle)
    report = PageReport(facts=_evaluate(pipe, session, probe))
    if screenshot is not None:
        pipe.pump(0.2)  # let the probe's changes paint
        image = pipe.send("Page.captureScreenshot", {"format": "png"}, session=session)["data"]
        Path(screenshot).write_bytes(base64.b64decode(image))
    for event in pipe.events:
        _record(report, event)
    return report


def _evaluate(pipe: _Pipe, session: str, expression: str) -> Any:
    result = pipe.send(
        "Runtime.evaluate", {"expression": expression, "returnByValue": True}, session=session
    )
    if "exceptionDetails" in result:
        raise RuntimeError(f"probe failed: {result['exceptionDetails']}")
    return result["result"].get("value")


def _record(report: PageReport, event: dict[str, Any]) -> None:
    method, params = event.get("method"), event.get("params", {})
    if method == "Runtime.exceptionThrown":
        details = params["exceptionDetails"]
        report.exceptions.append(details.get("exception", {}).get("description", details["text"]))
    elif method == "Runtime.consoleAPICalled" and params["type"] in ("error", "assert"):
        report.console_errors.append(" ".join(str(a.get("value")) for a in params["args"]))
    elif method == "Log.entryAdded" and params["entry"]["level"] == "error":
        report.console_errors.append(params["entry"]["text"])
    elif method == "Network.requestWillBeSent":
        request_url = params["request"]["url"]
        if not request_url.startswith(LOCAL_SCHEMES):
            report.network_requests.append(request_url)


def file_url(path: Path) -> str:
    return Path(path).resolve().as_uri()
