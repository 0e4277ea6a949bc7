"""Headless Chromium for the web view's tests: found or installed, then driven.

:func:`chromium` finds Debian's ``chromium`` (or another Chromium on PATH) and, when there is
none, installs it with ``apt-get install -y chromium`` (as root; ``apt-get update`` first if the
install alone fails), once per session and with a time limit. It answers None and the reason
only where no browser can be had; the tests then skip with that reason.

Two ways to drive it:

- :func:`dump_dom` and :func:`screenshot`: the command line (``--dump-dom`` / ``--screenshot``
  after ``--virtual-time-budget`` ms of the page's own time, so its scripts and fetches have
  run);
- :class:`Browser`: the DevTools protocol over ``--remote-debugging-pipe`` (JSON messages ended
  by a NUL on file descriptors 3 and 4; no extra package), to type into a form, click and wait
  for what the page shows, take a screenshot of the page as it is (:meth:`Browser.screenshot`)
  and read what it wrote to its console (:meth:`Browser.console_errors`).

WebGL (the web view's 3D view): headless Chromium has no GPU here, so it renders WebGL with
SwiftShader, Chromium's software renderer, asked for explicitly (``--use-angle=swiftshader
--enable-unsafe-swiftshader``): left to fall back to it on its own, Chromium 156 still draws,
but newer versions warn about or refuse that implicit fallback.
"""

from __future__ import annotations

import fcntl
import json
import os
import select
import shutil
import subprocess
import tempfile
import time
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
INSTALL_TIMEOUT = 900
"""Seconds apt-get may take to install Chromium (a few hundred MB on a fresh machine)."""

FLAGS = (
    "--headless",
    "--disable-gpu",
    "--no-sandbox",  # we run as root in a container
    "--hide-scrollbars",
    "--no-first-run",
    "--disable-dev-shm-usage",
    "--disable-extensions",
    "--mute-audio",
    "--use-angle=swiftshader",  # WebGL in software (SwiftShader), no GPU needed
    "--enable-unsafe-swiftshader",
)


def find_chromium() -> str | None:
    for name in NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


@cache
def chromium() -> tuple[str | None, str]:
    """(path of a Chromium, "") or (None, why none can be had). Installs Debian's if missing."""
    found = find_chromium()
    if found:
        return found, ""
    if not shutil.which("apt-get"):
        return None, "no Chromium on PATH and no apt-get to install Debian's chromium package"
    if os.geteuid() != 0:
        return None, "no Chromium on PATH, and installing Debian's chromium needs root"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = ["apt-get", "install", "-y", "-q", "chromium"]
    why = ""
    deadline = time.monotonic() + INSTALL_TIMEOUT
    for step in (install, ["apt-get", "update", "-q"], install):  # an update only if needed
        if find_chromium():
            break
        try:
            done = subprocess.run(
                step,
                env=env,
                capture_output=True,
                text=True,
                timeout=max(1.0, deadline - time.monotonic()),
            )
        except subprocess.TimeoutExpired:
            return None, f"'{' '.join(step)}' did not finish within {INSTALL_TIMEOUT} s"
        lines = (done.stderr or done.stdout).strip().splitlines()
        why = lines[-1] if lines else f"exit status {done.returncode}"
    found = find_chromium()
    if found:
        return found, ""
    return None, f"Debian's chromium package could not be installed: {why}"


def _run(args: list[str], timeout: float) -> subprocess.CompletedProcess[bytes]:
    path, why = chromium()
    if path is None:
        raise RuntimeError(why)
    with tempfile.TemporaryDirectory(prefix="chromium-") as profile:
        return subprocess.run(
            [path, *FLAGS, f"--user-data-dir={profile}", *args],
            capture_output=True,
            timeout=timeout,
            check=True,
        )


def dump_dom(url: str, *, budget_ms: int = 5000, timeout: float = 60) -> str:
    """The page's DOM as HTML once ``budget_ms`` of its virtual time has run."""
    done = _run([f"--virtual-time-budget={budget_ms}", "--dump-dom", url], timeout)
    return done.stdout.decode()


def screenshot(
    url: str,
    out: Path,
    *,
    size: tuple[int, int] = (1280, 1024),
    budget_ms: int = 5000,
    timeout: float = 60,
) -> Path:
    """A PNG of the page after ``budget_ms`` of its virtual time."""
    _run(
        [
            f"--virtual-time-budget={budget_ms}",
            f"--window-size={size[0]},{size[1]}",
            f"--screenshot={out}",
            url,
        ],
        timeout,
    )
    return out


def distinct_colours(png: Path) -> int:
    """How many distinct RGB colours a PNG holds (1 for a blank page)."""
    import matplotlib.pyplot as plt

    pixels = (plt.imread(png)[..., :3] * 255).round().astype(np.uint8).reshape(-1, 3)
    return len(np.unique(pixels, axis=0))


class Browser:
    """One headless Chromium driven over the DevTools protocol (a pipe, no network port)."""

    def __init__(self, timeout: float = 20):
        path, why = chromium()
        if path is None:
            raise RuntimeError(why)
        self.timeout = timeout
        self.profile = tempfile.TemporaryDirectory(prefix="chromium-")
        to_browser_r, self.to_browser = os.pipe()
        self.from_browser, from_browser_w = os.pipe()

        def fds() -> None:  # the browser reads commands on fd 3, writes answers on fd 4
            # Moved out of the way first: a pipe end may itself be fd 3 or 4.
            high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (to_browser_r, from_browser_w)]
            for target, fd in zip((3, 4), high, strict=True):
                os.dup2(fd, target)  # inheritable: survives the exec
                os.close(fd)

        self.process = subprocess.Popen(
            [path, *FLAGS, f"--user-data-dir={self.profile.name}", "--remote-debugging-pipe"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=fds,
            close_fds=False,  # would close 3 and 4 after fds(); Python's own fds are CLOEXEC
            start_new_session=True,
        )
        os.close(to_browser_r)
        os.close(from_browser_w)
        self.buffer = b""
        self.next_id = 0
        self.session: str | None = None
        self.events: list[dict[str, Any]] = []
        """Every event the browser sent (``method``, ``params``), in order."""

    def call(self, method: str, params: dict[str, Any] | None = None, *, top: bool = False) -> Any:
        """Send one command (to the attached page unless ``top``) and return its result."""
        self.next_id += 1
        message: dict[str, Any] = {"id": self.next_id, "method": method, "params": params or {}}
        if self.session and not top:
            message["sessionId"] = self.session
        os.write(self.to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + self.timeout
        while True:
            while b"\0" not in self.buffer:
                left = deadline - time.monotonic()
                ready, _, _ = select.select([self.from_browser], [], [], max(0.0, left))
                if not ready:
                    raise TimeoutError(f"no answer to {method} within {self.timeout} s")
                chunk = os.read(self.from_browser, 1 << 16)
                if not chunk:
                    raise RuntimeError("the browser closed its pipe")
                self.buffer += chunk
            raw, self.buffer = self.buffer.split(b"\0", 1)
            answer = json.loads(raw)
            if answer.get("id") == self.next_id:
                if "error" in answer:
                    raise RuntimeError(f"{method}: {answer['error']}")
                return answer.get("result", {})
            if "method" in answer:
                self.events.append(answer)

    def open(self, url: str) -> None:
        """Open ``url`` in a new page and attach to it."""
        target = self.call("Target.createTarget", {"url": "about:blank"}, top=True)["targetId"]
        attached = self.call(
            "Target.attachToTarget", {"targetId": target, "flatten": True}, top=True
        )
        self.session = attached["sessionId"]
        self.call("Page.enable")
        self.call("Runtime.enable")  # console messages and uncaught exceptions, as events
        self.call("Log.enable")  # the browser's own: CSP violations, failed loads, WebGL
        self.call("Page.navigate", {"url": url})

    def console_errors(self) -> list[str]:
        """What the page reported as errors so far: console.error calls, uncaught exceptions
        and the browser's error log entries (a refused resource, a CSP violation, ...)."""
        self.js("0")  # reads the pipe up to now
        found = []
        for event in self.events:
            params = event.get("params", {})
            if event["method"] == "Runtime.consoleAPICalled" and params.get("type") == "error":
                found.append(
                    " ".join(str(a.get("value", a.get("description"))) for a in params["args"])
                )
            elif event["method"] == "Runtime.exceptionThrown":
                details = params.get("exceptionDetails", {})
                found.append(str(details.get("exception", {}).get("description") or details))
            elif event["method"] == "Log.entryAdded" and params["entry"]["level"] == "error":
                found.append(f"{params['entry'].get('source')}: {params['entry']['text']}")
        return found

    def screenshot(self, out: Path) -> Path:
        """A PNG of the page's viewport as it is now (WebGL canvases included)."""
        import base64

        shot = self.call("Page.captureScreenshot", {"format": "png"})
        out.write_bytes(base64.b64decode(shot["data"]))
        return out

    def viewport(self, width: int, height: int) -> None:
        """Lay the page out at ``width`` x ``height`` CSS pixels (1 device pixel each)."""
        self.call(
            "Emulation.setDeviceMetricsOverride",
            {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
        )

    def js(self, expression: str) -> Any:
        """Evaluate ``expression`` in the page (promises awaited) and return its value."""
        result = self.call(
            "Runtime.evaluate",
            {"expression": expression, "awaitPromise": True, "returnByValue": True},
        )
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout: float | None = None) -> Any:
        """Poll ``expression`` until it is truthy; its value (true for an element)."""
        deadline = time.monotonic() + (timeout or self.timeout)
        while True:
            try:  # an element would come back as an empty (falsy) value
                value = self.js(f"(v => v instanceof Node ? true : v)({expression})")
            except RuntimeError:
                value = None  # e.g. the page is still loading
            if value:
                return value
            if time.monotonic() > deadline:
                text = self.js("document.body ? document.body.innerText : ''")
                raise TimeoutError(f"never true: {expression}\npage text:\n{text}")
            time.sleep(0.1)

    def close(self) -> None:
        try:
            self.call("Browser.close", top=True)
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, 9)
            self.process.wait()
        os.close(self.to_browser)
        os.close(self.from_browser)
        self.profile.cleanup()

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
