"""Headless Chromium driven over the Chrome DevTools Protocol (a websocket to the browser), for the
tests that open the HTML report in a real browser.

The browser runs in its own process group with a fresh profile folder, on a debugging port it picks
itself (``--remote-debugging-port=0``, read back from the profile's ``DevToolsActivePort``), with no
network access needed: the page is a local file. Leaving the ``with`` block closes the browser
(``Browser.close``, then SIGKILL to its process group if it is still there), whatever happened inside.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import websocket

# the executables looked for on the PATH, in this order (CHROMIUM, a path, comes first when set)
CANDIDATES = ("chromium", "chromium-browser", "google-chrome-stable", "google-chrome")


def find_chromium() -> str | None:
    """Path of a Chromium executable: $CHROMIUM when set, else the first of CANDIDATES on the PATH."""
    explicit = os.environ.get("CHROMIUM")
    if explicit:
        return explicit if os.access(explicit, os.X_OK) else None
    for name in CANDIDATES:
        found = shutil.which(name)
        if found:
            return found
    return None


class BrowserError(RuntimeError):
    """The browser did not start, answered with an error, or did not answer in time."""


class Chromium:
    """One headless Chromium with one page (tab) attached; ``events`` collects every protocol event
    of that page (method and params) in the order received."""

    def __init__(self, executable: str, profile_dir: Path, width_px: int = 1280, height_px: int = 800,
                 timeout_s: float = 60.0):
        self.executable = executable
        self.profile_dir = Path(profile_dir)
        self.width_px, self.height_px = width_px, height_px
        self.timeout_s = timeout_s
        self.events: list[dict] = []
        self._proc: subprocess.Popen | None = None
        self._ws: websocket.WebSocket | None = None
        self._session: str | None = None
        self._next_id = 0
        self._pgid: int | None = None
        # live processes of the browser found after close() (an empty list when it cleaned up)
        self.leftover_pids_after_close: list[int] | None = None

    # --- process ------------------------------------------------------------------------------
    def __enter__(self) -> Chromium:
        try:
            self._start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _start(self) -> None:
        self.profile_dir.mkdir(parents=True, exist_ok=False)     # unique and empty: nothing shared with another run
        user_data = self.profile_dir / "user-data"
        log = open(self.profile_dir / "stderr.log", "wb")
        args = [self.executable, "--headless", "--remote-debugging-port=0", f"--user-data-dir={user_data}",
                "--no-first-run", "--no-default-browser-check",
                "--no-sandbox",                     # root in a container has no user namespace to sandbox in
                "--disable-crash-reporter", "--disable-gpu", "--disable-dev-shm-usage", "--disable-extensions",
                "--disable-sync", "--disable-background-networking", "--disable-component-update", "--mute-audio",
                "--hide-scrollbars", f"--window-size={self.width_px},{self.height_px}", "about:blank"]
        # the crash handler's database and every cache under the profile folder: the handler starts in a
        # session of its own, and its command line then names the folder (see leftover_pids); nothing is
        # written to $HOME
        env = {**os.environ, "XDG_CONFIG_HOME": str(self.profile_dir / "config"),
               "XDG_CACHE_HOME": str(self.profile_dir / "cache")}
        self._proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=log, stderr=log, env=env,
                                      start_new_session=True)
        self._pgid = self._proc.pid                 # start_new_session: the browser leads its own group
        log.close()
        port_file = user_data / "DevToolsActivePort"
        deadline = time.monotonic() + self.timeout_s
        while True:
            if self._proc.poll() is not None:
                raise BrowserError(f"{self.executable} exited with code {self._proc.returncode} on start "
                                   f"(see {log.name})")
            lines = port_file.read_text().split() if port_file.exists() else []
            if len(lines) >= 2:
                break
            if time.monotonic() > deadline:
                raise BrowserError(f"{self.executable} wrote no DevToolsActivePort within {self.timeout_s} s")
            time.sleep(0.05)
        port, path = lines[0], lines[1]
        # no Origin header: Chromium refuses websocket clients that send one it was not told to allow
        self._ws = websocket.create_connection(f"ws://127.0.0.1:{port}{path}", timeout=self.timeout_s,
                                               suppress_origin=True)
        target = self.call("Target.createTarget", url="about:blank", browser=True)["targetId"]
        self._session = self.call("Target.attachToTarget", targetId=target, flatten=True,
                                  browser=True)["sessionId"]
        for domain in ("Page", "Runtime", "Log", "Network"):
            self.call(f"{domain}.enable")
        self.call("Emulation.setDeviceMetricsOverride", width=self.width_px, height=self.height_px,
                  deviceScaleFactor=1, mobile=False)

    def close(self) -> None:
        """Close the browser politely, then make sure its whole process group is gone."""
        if self._ws is not None:
            try:
                self.call("Browser.close", browser=True, timeout_s=5.0)
            except Exception:   # the browser may already be gone; the kill below follows
                pass
            try:
                self._ws.close()
            except Exception:
                pass
            self._ws = None
        if self._proc is not None:
            try:
                self._proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                pass
            try:
                os.killpg(self._pgid, signal.SIGKILL)     # the group this Popen started, by its id
            except ProcessLookupError:
                pass
            self._proc.wait(timeout=10.0)
            for pid in self.leftover_pids():                   # a helper that left the group, by its id
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + 10.0
            while self.leftover_pids() and time.monotonic() < deadline:
                time.sleep(0.05)
            self.leftover_pids_after_close = self.leftover_pids()
            self._proc = None

    def leftover_pids(self) -> list[int]:
        """Live (not zombie) processes of this browser: in its process group, or started with its profile
        folder on their command line (a helper that moved to a session of its own)."""
        if self._pgid is None or not Path("/proc").is_dir():      # without /proc only the group kill is left
            return []
        pids = []
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            if int(entry.name) == os.getpid():
                continue
            try:
                stat = (entry / "stat").read_text()
                argv = (entry / "cmdline").read_bytes().decode(errors="replace").split("\0")
            except OSError:        # gone meanwhile, or not ours to read
                continue
            fields = stat[stat.rindex(")") + 2:].split()       # after "pid (comm) ": state, ppid, pgrp, ...
            if fields[0] == "Z":
                continue
            # an option naming the profile folder (--user-data-dir=..., the crash handler's --database=...),
            # not any mention of it (a shell or a script that names the folder in its text)
            in_profile = any(a.startswith("--") and str(self.profile_dir) in a for a in argv)
            if int(fields[2]) == self._pgid or in_profile:
                pids.append(int(entry.name))
        return pids

    # --- protocol -----------------------------------------------------------------------------
    def call(self, method: str, browser: bool = False, timeout_s: float | None = None, **params) -> dict:
        """Send one command (to the page's session, or to the browser with ``browser=True``) and return
        its result; events that arrive meanwhile go to ``events``."""
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params}
        if not browser:
            message["sessionId"] = self._session
        self._ws.send(json.dumps(message))
        deadline = time.monotonic() + (timeout_s or self.timeout_s)
        while True:
            reply = self._receive(deadline, method)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def wait_for_event(self, method: str, timeout_s: float | None = None) -> dict:
        """The params of the first event ``method`` received (already, or from now on)."""
        for event in self.events:
            if event["method"] == method:
                return event["params"]
        deadline = time.monotonic() + (timeout_s or self.timeout_s)
        while True:
            message = self._receive(deadline, method)
            if message.get("method") == method:
                return message["params"]

    def _receive(self, deadline: float, waiting_for: str) -> dict:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise BrowserError(f"no answer to {waiting_for} in time")
        self._ws.settimeout(remaining)
        try:
            message = json.loads(self._ws.recv())
        except websocket.WebSocketTimeoutException as err:
            raise BrowserError(f"no answer to {waiting_for} in time") from err
        if "method" in message:
            self.events.append({"method": message["method"], "params": message.get("params", {})})
        return message

    # --- page ---------------------------------------------------------------------------------
    def open(self, path: Path) -> None:
        """Load a local file and wait for its load event (every image of the page fetched)."""
        self.events.clear()
        result = self.call("Page.navigate", url=Path(path).resolve().as_uri())
        if result.get("errorText"):
            raise BrowserError(f"{path}: {result['errorText']}")
        self.wait_for_event("Page.loadEventFired")

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (promises awaited), as JSON."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise BrowserError(f"script failed: {result['exceptionDetails'].get('text')} "
                               f"{result['exceptionDetails'].get('exception', {}).get('description', '')}")
        return result["result"].get("value")

    def screenshot_png(self) -> bytes:
        """The viewport as PNG."""
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def errors(self) -> list[str]:
        """Console errors, uncaught exceptions and failed requests of the page, one line each."""
        out = []
        urls = {e["params"].get("requestId"): e["params"].get("request", {}).get("url", "")
                for e in self.events if e["method"] == "Network.requestWillBeSent"}
        for event in self.events:
            method, params = event["method"], event["params"]
            if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
                text = " ".join(str(a.get("value", a.get("description", ""))) for a in params.get("args", []))
                out.append(f"console.{params['type']}: {text}")
            elif method == "Runtime.exceptionThrown":
                details = params.get("exceptionDetails", {})
                out.append(f"exception: {details.get('exception', {}).get('description', details.get('text'))}")
            elif method == "Log.entryAdded" and params.get("entry", {}).get("level") == "error":
                entry = params["entry"]
                out.append(f"log ({entry.get('source')}): {entry.get('text')} {entry.get('url', '')}".rstrip())
            elif method == "Network.loadingFailed" and not params.get("canceled"):
                url = urls.get(params.get("requestId"), "?")
                out.append(f"request failed: {params.get('errorText')} ({params.get('type')}) {url[:120]}")
        return out
