"""The viewer's web server: the page, its script, three.js and one glb, on 127.0.0.1 only."""

import errno
import html
import http.server
import os
import threading
import urllib.parse
from collections.abc import Callable
from pathlib import Path

from ._glb import GlbSummary, inspect_glb

HOST = "127.0.0.1"
"""The only address the viewer listens on (loopback: nothing off this machine can reach it)."""

STATIC_DIR = Path(__file__).resolve().parent / "static"
"""The page, its script and the vendored three.js (package data)."""

MODEL_PATH = "/model.glb"
_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".glb": "model/gltf-binary",
    ".LICENSE": "text/plain; charset=utf-8",
}


class _Handler(http.server.BaseHTTPRequestHandler):
    server: "_Server"
    server_version = "canrig-view"
    sys_version = ""

    def do_GET(self):  # noqa: N802 (http.server's name)
        self._answer(body=True)

    def do_HEAD(self):  # noqa: N802
        self._answer(body=False)

    def _answer(self, body: bool) -> None:
        path = urllib.parse.unquote(urllib.parse.urlsplit(self.path).path)
        segments = path.replace("\\", "/").split("/")
        if ".." in segments:
            self.send_error(403, "paths outside the served folder are refused")
            return
        if path in ("/", "/index.html"):
            name = html.escape(self.server.summary.path.name)
            text = (STATIC_DIR / "index.html").read_text(encoding="utf-8")
            data = text.replace("<title>canrig view</title>", f"<title>{name}</title>").encode()
            kind = _TYPES[".html"]
        elif path == MODEL_PATH:
            data, kind = self.server.summary.path.read_bytes(), _TYPES[".glb"]
        else:
            file = (STATIC_DIR / path.lstrip("/")).resolve()
            if file.parent != STATIC_DIR or not file.is_file():
                self.send_error(404, "not found")
                return
            data, kind = file.read_bytes(), _TYPES.get(file.suffix, "application/octet-stream")
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if body:
            self.wfile.write(data)

    def log_message(self, format, *args):  # noqa: A002 (http.server's signature)
        if self.server.log is not None:
            self.server.log(f"{self.address_string()} {format % args}")


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True
    summary: GlbSummary
    log: Callable[[str], None] | None = None


class ViewerServer:
    """Serve the viewer page for one ``.glb`` on ``http://127.0.0.1:PORT/``.

    ``port=0`` takes a free port. Use as a context manager (``with ViewerServer(f) as s:``) or
    call ``start()`` and ``stop()``; ``stop()`` closes the socket and joins the server thread.

    Raises ValueError naming the file when it is not a glb with a mesh (``inspect_glb``) and
    naming the port when it is out of range or in use."""

    def __init__(
        self, glb: str | os.PathLike, *, port: int = 0, log: Callable[[str], None] | None = None
    ):
        self.summary = inspect_glb(glb)
        if not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"--port {port}: expected a port number 0-65535 (0: any free port)")
        try:
            self._server = _Server((HOST, port), _Handler)
        except OSError as error:
            if error.errno == errno.EADDRINUSE:
                raise ValueError(
                    f"--port {port}: already in use on {HOST} (another server listens there; "
                    "choose another port or --port 0 for a free one)"
                ) from None
            raise ValueError(f"--port {port}: cannot listen on {HOST}: {error}") from None
        self._server.summary, self._server.log = self.summary, log
        self._thread: threading.Thread | None = None

    @property
    def address(self) -> tuple[str, int]:
        host, port = self._server.server_address[:2]
        return str(host), int(port)

    @property
    def url(self) -> str:
        host, port = self.address
        return f"http://{host}:{port}/"

    def start(self) -> "ViewerServer":
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving, close the listening socket and join the thread (idempotent)."""
        if self._thread is not None:
            self._server.shutdown()
            self._thread.join()
            self._thread = None
        self._server.server_close()

    def __enter__(self) -> "ViewerServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
