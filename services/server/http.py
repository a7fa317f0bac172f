"""The render server's status page: a small read-only HTTP endpoint for
watching a render from a browser (like Tungsten's server, which serves
`/status` as a snapshot copied under a lock).

Served
------
    GET /              one self-contained HTML page (no external resources)
                       that polls /status and reloads /preview.png every 2 s
    GET /status        json.dumps(status()), application/json, no-store
    GET /preview.png   preview_png() as image/png, no-store; 503 while it
                       returns None (no image yet)

HEAD is answered like GET without a body. Query strings are ignored when
routing, so the page can bust caches with `/preview.png?t=...`.

Why read-only: the endpoint has no authentication and the render is
steered only through the wire protocol, so nothing here may change the
server's state. Every other method gets 405 (with `Allow: GET, HEAD`) and
the callables are not even called. It binds to loopback by default; expose
it with an SSH tunnel rather than `host="0.0.0.0"`.

The page itself is services/server/page.py (the keys it reads are listed
there; services/server/history.py adds the derived ones to the server's
status). Non-finite floats (an unknown ETA) are sent as null, because JSON
has no Infinity and browsers refuse it.

API
---
    StatusServer(status, preview_png, host="127.0.0.1", port=0)
    .start() -> self; .url -> "http://HOST:PORT/"; .close()
"""
from __future__ import annotations

import json
import logging
import math
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Callable
from urllib.parse import urlsplit

from services.server.page import PAGE

log = logging.getLogger("dosppm.http")

ALLOWED_METHODS = "GET, HEAD"
TEXT = "text/plain; charset=utf-8"


class StatusServer:
    """Serves `status()` and `preview_png()` on a daemon thread. The socket
    is bound in the constructor, so `url` holds the real port (port 0 picks
    an ephemeral one) before `start()`."""

    def __init__(self, status: Callable[[], dict], preview_png: Callable[[], bytes | None],
                 host: str = "127.0.0.1", port: int = 0):
        self._httpd = _Server((host, port), _Handler)
        self._httpd.status = status
        self._httpd.preview_png = preview_png
        self._thread: threading.Thread | None = None

    def start(self) -> "StatusServer":
        # A short poll interval keeps close() quick: shutdown() waits for it.
        self._thread = threading.Thread(target=self._httpd.serve_forever, args=(0.1,),
                                        name="dosppm-http", daemon=True)
        self._thread.start()
        return self

    @property
    def url(self) -> str:
        host, port = self._httpd.server_address[:2]
        return f"http://{host}:{port}/"

    def close(self) -> None:
        # shutdown() waits for serve_forever to notice, so it would hang on a
        # server that was never started.
        if self._thread is not None:
            self._httpd.shutdown()
            self._thread.join()
            self._thread = None
        self._httpd.server_close()

    def __enter__(self) -> "StatusServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


class _Server(ThreadingHTTPServer):
    # A browser left open must not keep the render server from exiting.
    daemon_threads = True
    status: Callable[[], dict]
    preview_png: Callable[[], bytes | None]

    def handle_error(self, request, client_address) -> None:
        # A client hanging up mid-reply is routine; keep it off stderr.
        log.debug("request from %s failed", client_address, exc_info=True)


class _Handler(BaseHTTPRequestHandler):
    server: _Server

    def do_GET(self) -> None:
        self._route(send_body=True)

    def do_HEAD(self) -> None:
        self._route(send_body=False)

    def __getattr__(self, name: str):
        # The base class answers methods without a do_X with 501; every
        # method other than GET and HEAD is refused the same way instead.
        if name.startswith("do_"):
            return self._refuse
        raise AttributeError(name)

    def _refuse(self) -> None:
        # Connection: close, because a request body we never read would
        # otherwise be parsed as the next request.
        self._reply(405, b"method not allowed: this endpoint is read-only\n",
                    TEXT, {"Allow": ALLOWED_METHODS, "Connection": "close"})

    def _route(self, send_body: bool) -> None:
        path = urlsplit(self.path).path
        routes = {"/": self._page, "/index.html": self._page,
                  "/status": self._status, "/preview.png": self._preview}
        handler = routes.get(path)
        if handler is None:
            code, body, ctype = 404, b"not found\n", TEXT
        else:
            code, body, ctype = handler()
        self._reply(code, body, ctype, send_body=send_body)

    def _page(self) -> tuple[int, bytes, str]:
        return 200, PAGE.encode("utf-8"), "text/html; charset=utf-8"

    def _status(self) -> tuple[int, bytes, str]:
        try:
            body = json.dumps(_jsonable(self.server.status()), allow_nan=False)
        except Exception as e:
            # The render must not notice a failing snapshot; the page shows it.
            log.warning("status snapshot failed", exc_info=True)
            body = json.dumps({"error": f"status failed: {type(e).__name__}: {e}"})
            return 500, body.encode("utf-8"), "application/json"
        return 200, body.encode("utf-8"), "application/json"

    def _preview(self) -> tuple[int, bytes, str]:
        try:
            png = self.server.preview_png()
        except Exception as e:
            log.warning("preview failed", exc_info=True)
            return 500, f"preview failed: {type(e).__name__}\n".encode(), TEXT
        if png is None:
            return 503, b"no preview image yet\n", TEXT
        return 200, bytes(png), "image/png"

    def _reply(self, code: int, body: bytes, content_type: str,
               headers: dict[str, str] | None = None, send_body: bool = True) -> None:
        self.send_response(code)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        # Every answer is a snapshot of a render in progress.
        self.send_header("Cache-Control", "no-store")
        for name, value in (headers or {}).items():
            self.send_header(name, value)
        self.end_headers()
        if send_body:
            self.wfile.write(body)

    def log_message(self, format: str, *args) -> None:
        log.debug("%s " + format, self.address_string(), *args)


def _jsonable(value):
    """`value` with numpy scalars and arrays made plain and non-finite floats
    made None (JSON has no Infinity, and an unknown ETA is one)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (str, int, bool)) or value is None:
        return value
    if hasattr(value, "tolist"):
        return _jsonable(value.tolist())
    return value
