"""Headless Chromium driven through the Chrome DevTools protocol over a pipe.

Chromium's ``--remote-debugging-pipe`` reads commands on file descriptor 3 and writes answers
and events on 4, each a JSON message ending in a NUL byte: no port is opened and nothing but
the standard library is needed. The browser is the system's (Debian: ``apt-get install
chromium-headless-shell`` or ``chromium``); nothing is downloaded at run time. WebGL runs on
SwiftShader, Chromium's CPU renderer, so no GPU is needed.
"""

import base64
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

CHROMIUM_ENV_VAR = "CANRIG_CHROMIUM"
"""An explicit Chromium (or Chrome) executable, tried before the names on ``PATH``."""

CHROMIUM_NAMES = (
    "chromium-headless-shell",
    "chromium",
    "chromium-browser",
    "google-chrome",
    "google-chrome-stable",
)

INSTALL_HINT = (
    "install one from the system packages (Debian/Ubuntu: apt-get install "
    f"chromium-headless-shell, or chromium) or set ${CHROMIUM_ENV_VAR} to its executable"
)

# Puts the two pipe ends on descriptors 3 and 4, then becomes the browser (run with -I -S).
_EXEC_WITH_PIPES = (
    "import fcntl, os, sys\n"
    "r = fcntl.fcntl(int(sys.argv[1]), fcntl.F_DUPFD_CLOEXEC, 10)\n"
    "w = fcntl.fcntl(int(sys.argv[2]), fcntl.F_DUPFD_CLOEXEC, 10)\n"
    "os.dup2(r, 3); os.dup2(w, 4)\n"
    "os.execv(sys.argv[3], sys.argv[3:])\n"
)


class BrowserError(RuntimeError):
    """Chromium failed: it did not start, a command failed or timed out, or it crashed."""


def find_chromium() -> str | None:
    """The Chromium executable: ``$CANRIG_CHROMIUM``, else the first of ``CHROMIUM_NAMES`` on
    ``PATH``; None when there is none."""
    explicit = os.environ.get(CHROMIUM_ENV_VAR)
    if explicit:
        return explicit if shutil.which(explicit) else None
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


class HeadlessChromium:
    """A headless Chromium with one page (a DevTools session), closed by ``close()`` or on
    leaving a ``with`` block.

    ``console`` collects the page's console messages, uncaught exceptions and browser log
    entries as ``(level, text)``; ``errors`` are those of level ``error``."""

    def __init__(
        self,
        executable: str | None = None,
        *,
        width: int = 960,
        height: int = 720,
        timeout: float = 60.0,
    ):
        executable = executable or find_chromium()
        if executable is None:
            raise BrowserError(f"no headless Chromium found: {INSTALL_HINT}")
        self.timeout = timeout
        self.console: list[tuple[str, str]] = []
        self._profile = tempfile.mkdtemp(prefix="canrig-chromium-")
        self._log = open(Path(self._profile) / "chromium.log", "wb")  # noqa: SIM115
        command_read, self._command_write = os.pipe()
        self._answer_read, answer_write = os.pipe()
        flags = [
            "--headless",
            "--remote-debugging-pipe",
            f"--user-data-dir={self._profile}",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--ignore-gpu-blocklist",
            f"--window-size={width},{height}",
            "--hide-scrollbars",
            "--disable-dev-shm-usage",  # containers often have a tiny /dev/shm
            "--no-first-run",
            "--no-default-browser-check",
            "--disable-extensions",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--mute-audio",
        ]
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            flags.append("--no-sandbox")  # Chromium's sandbox refuses to run as root
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-I", "-S", "-c", _EXEC_WITH_PIPES]
                + [str(command_read), str(answer_write), executable, *flags, "about:blank"],
                pass_fds=(command_read, answer_write),
                stdin=subprocess.DEVNULL,
                stdout=self._log,
                stderr=self._log,
            )
        except OSError as error:
            os.close(self._command_write)
            os.close(self._answer_read)
            shutil.rmtree(self._profile, ignore_errors=True)
            raise BrowserError(f"{executable}: cannot start Chromium ({error})") from None
        finally:
            os.close(command_read)
            os.close(answer_write)
        self._lock = threading.Condition()
        self._answers: dict[int, dict] = {}
        self._events: list[dict] = []
        self._next_id = 0
        self._closed = False
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        try:
            target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
            attached = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})
            self._session = attached["sessionId"]
            for domain in ("Page", "Runtime", "Log"):
                self.send(f"{domain}.enable", session=True)
            self.send(
                "Emulation.setDeviceMetricsOverride",
                {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
                session=True,
            )
        except BaseException:
            self.close()
            raise

    # -- the pipe ---------------------------------------------------------------------------
    def _read(self) -> None:
        pending = b""
        with open(self._answer_read, "rb", buffering=0) as pipe:
            while True:
                chunk = pipe.read(1 << 16)
                if not chunk:
                    break
                pending += chunk
                *messages, pending = pending.split(b"\0")
                for raw in messages:
                    self._dispatch(json.loads(raw))
        with self._lock:
            self._closed = True
            self._lock.notify_all()

    def _dispatch(self, message: dict) -> None:
        method, params = message.get("method"), message.get("params", {})
        if method == "Runtime.consoleAPICalled":
            kind = str(params["type"])
            level = {"warning": "warning", "assert": "error"}.get(kind, kind)
            text = " ".join(
                str(a.get("value", a.get("description", a.get("type"))))
                for a in params.get("args", [])
            )
            self.console.append((level, text))
        elif method == "Runtime.exceptionThrown":
            details = params["exceptionDetails"]
            text = details.get("exception", {}).get("description") or details.get("text", "")
            self.console.append(("error", f"uncaught: {text}"))
        elif method == "Log.entryAdded":
            entry = params["entry"]
            text = entry["text"] + (f" ({entry['url']})" if entry.get("url") else "")
            self.console.append((entry["level"], text))
        with self._lock:
            if "id" in message:
                self._answers[message["id"]] = message
            else:
                self._events.append(message)
            self._lock.notify_all()

    def send(self, method: str, params: dict | None = None, *, session: bool = False) -> dict:
        """Send one DevTools command (to the page's session when ``session``); its result."""
        with self._lock:
            if self._closed:
                raise BrowserError(f"Chromium has exited ({self._tail()})")
            self._next_id += 1
            ident = self._next_id
        message = {"id": ident, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = self._session
        write = self._command_write
        if write is None:  # closed
            raise BrowserError(f"Chromium has exited ({self._tail()})")
        try:
            os.write(write, json.dumps(message).encode() + b"\0")
        except OSError as error:
            raise BrowserError(f"{method}: cannot talk to Chromium ({error})") from None
        deadline = time.monotonic() + self.timeout
        with self._lock:
            while ident not in self._answers:
                left = deadline - time.monotonic()
                if self._closed or left <= 0:
                    why = "Chromium exited" if self._closed else f"no answer in {self.timeout} s"
                    raise BrowserError(f"{method}: {why} ({self._tail()})")
                self._lock.wait(left)
            answer = self._answers.pop(ident)
        if "error" in answer:
            raise BrowserError(f"{method}: {answer['error'].get('message', answer['error'])}")
        return answer.get("result", {})

    def _tail(self) -> str:
        try:
            text = (Path(self._profile) / "chromium.log").read_text(errors="replace")
        except OSError:
            return "no log"
        return text.strip().splitlines()[-1] if text.strip() else "no log"

    def wait_event(self, method: str, since: int = 0) -> dict:
        """The first event ``method`` at or after index ``since`` of the events received."""
        deadline = time.monotonic() + self.timeout
        with self._lock:
            while True:
                for event in self._events[since:]:
                    if event.get("method") == method:
                        return event
                left = deadline - time.monotonic()
                if self._closed or left <= 0:
                    raise BrowserError(f"waiting for {method}: no such event ({self._tail()})")
                self._lock.wait(left)

    # -- the page ---------------------------------------------------------------------------
    def navigate(self, url: str) -> None:
        """Load ``url`` and wait for its load event."""
        with self._lock:
            since = len(self._events)
        result = self.send("Page.navigate", {"url": url}, session=True)
        if result.get("errorText"):
            raise BrowserError(f"{url}: {result['errorText']}")
        self.wait_event("Page.loadEventFired", since)

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (promises awaited)."""
        result = self.send(
            "Runtime.evaluate",
            {"expression": expression, "awaitPromise": True, "returnByValue": True},
            session=True,
        )
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            text = details.get("exception", {}).get("description") or details.get("text")
            raise BrowserError(f"in the page: {text}")
        return result["result"].get("value")

    def screenshot(self) -> bytes:
        """The page's viewport as PNG bytes."""
        data = self.send("Page.captureScreenshot", {"format": "png"}, session=True)["data"]
        return base64.b64decode(data)

    @property
    def errors(self) -> list[str]:
        return [text for level, text in self.console if level == "error"]

    def close(self) -> None:
        """Close the browser (politely, then by force) and remove its profile (idempotent)."""
        if self._command_write is None:
            return
        if self._process.poll() is None:
            try:
                os.write(self._command_write, b'{"id": 0, "method": "Browser.close"}\0')
            except OSError:
                pass
            try:
                self._process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        os.close(self._command_write)
        self._command_write = None
        self._reader.join(timeout=10)
        self._log.close()
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> "HeadlessChromium":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
