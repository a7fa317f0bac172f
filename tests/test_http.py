"""The read-only status endpoint (services/http.py): /status and
/preview.png serve the callables' snapshots, every other method is refused
without calling them, a failing snapshot is a 500 and not a dead server,
and in a headless Chromium the page really fetches /status and fills
itself in."""
from __future__ import annotations

import http.client
import json
import shutil
import socket
import subprocess
import urllib.error
import urllib.request
from html.parser import HTMLParser
from urllib.parse import urlsplit

import numpy as np
import pytest

from dosppm_core.film import encode_png
from services.server.http import StatusServer

pytestmark = pytest.mark.timeout(120)

PNG = encode_png(np.zeros((4, 4, 3), np.uint8))
STATUS = {
    "iteration": 7, "photons_emitted": 123456, "photons_committed": 120000,
    "photons_per_s": 98765.4, "hit_points_per_s": 4321.0, "jobs_in_flight": 3,
    "eta_s": 42.0,
    "tracers": [{"id": "tracer-a", "chunks": 5, "queue": 2, "load": 0.75},
                {"id": "tracer-b", "chunks": 4, "queue": 0, "load": 0.25}],
}


class Source:
    """The server's side: a status snapshot and a preview, counting calls."""

    def __init__(self, status=STATUS, png=PNG):
        self.status_value, self.png = status, png
        self.calls = 0

    def status(self) -> dict:
        self.calls += 1
        if isinstance(self.status_value, Exception):
            raise self.status_value
        return self.status_value

    def preview_png(self) -> bytes | None:
        self.calls += 1
        return self.png


@pytest.fixture
def source():
    return Source()


@pytest.fixture
def server(source):
    srv = StatusServer(source.status, source.preview_png).start()
    yield srv
    srv.close()


def get(url: str) -> tuple[int, dict, bytes]:
    """(status code, headers, body), for error codes too."""
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def request(url: str, method: str, body: bytes | None = None):
    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=10)
    try:
        conn.request(method, "/status", body=body)
        r = conn.getresponse()
        return r.status, dict(r.headers), r.read()
    finally:
        conn.close()


# -- routes ----------------------------------------------------------------------
def test_status_is_the_dict_as_json(server):
    code, headers, body = get(server.url + "status")
    assert code == 200
    assert headers["Content-Type"] == "application/json"
    assert headers["Cache-Control"] == "no-store"
    assert json.loads(body) == STATUS


def test_status_makes_numpy_and_infinity_json(source, server):
    source.status_value = {"eta_s": float("inf"), "photons": np.int64(5),
                           "load": np.float32(0.5), "queue": np.arange(3)}
    code, _, body = get(server.url + "status")
    assert code == 200
    assert json.loads(body) == {"eta_s": None, "photons": 5, "load": 0.5, "queue": [0, 1, 2]}


def test_preview_is_the_png(server):
    code, headers, body = get(server.url + "preview.png")
    assert code == 200
    assert headers["Content-Type"] == "image/png"
    assert headers["Cache-Control"] == "no-store"
    assert body == PNG


def test_preview_ignores_query_string(server):
    code, _, body = get(server.url + "preview.png?t=1712345678901")
    assert (code, body) == (200, PNG)


def test_preview_is_503_before_an_image_exists(source, server):
    source.png = None
    code, headers, body = get(server.url + "preview.png")
    assert code == 503
    assert headers["Content-Type"].startswith("text/plain")
    assert body.strip()


def test_unknown_path_is_404(server):
    assert get(server.url + "nothing-here")[0] == 404
    assert get(server.url + "status/extra")[0] == 404


def test_head_has_headers_and_no_body(server):
    code, headers, body = request(server.url, "HEAD")
    assert (code, body) == (200, b"")
    assert int(headers["Content-Length"]) == len(json.dumps(STATUS))


@pytest.mark.parametrize("method", ["POST", "PUT", "DELETE", "PATCH", "FROB"])
def test_other_methods_are_405_and_change_nothing(source, server, method):
    before = get(server.url + "status")[2]
    calls = source.calls
    code, headers, _ = request(server.url, method, body=b'{"iteration": 0}')
    assert code == 405
    assert headers["Allow"] == "GET, HEAD"
    assert source.calls == calls
    assert get(server.url + "status")[2] == before


def test_failing_status_is_500_and_server_keeps_serving(source, server):
    source.status_value = RuntimeError("snapshot\nbroke")
    code, headers, body = get(server.url + "status")
    assert code == 500
    assert headers["Content-Type"] == "application/json"
    assert b"\n" not in body
    assert "snapshot" in json.loads(body)["error"]
    source.status_value = STATUS
    assert get(server.url + "status")[0] == 200


def test_page_is_self_contained(server):
    code, headers, body = get(server.url)
    page = body.decode()
    assert code == 200 and headers["Content-Type"].startswith("text/html")
    for element_id in ("iteration", "photons", "committed", "tracers", "preview",
                       "progress", "chart_photons"):
        assert f'id="{element_id}"' in page
    assert "http://" not in page and "https://" not in page


# -- binding ---------------------------------------------------------------------
def test_binds_loopback_on_an_ephemeral_port(source):
    srv = StatusServer(source.status, source.preview_png)
    try:
        parts = urlsplit(srv.url)
        assert parts.hostname == "127.0.0.1"
        assert parts.port > 0 and srv.url.endswith("/")
    finally:
        srv.close()


def test_close_frees_the_port(source):
    srv = StatusServer(source.status, source.preview_png).start()
    port = urlsplit(srv.url).port
    assert get(srv.url + "status")[0] == 200
    srv.close()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=2).close()
    again = StatusServer(source.status, source.preview_png, port=port).start()
    try:
        assert get(again.url + "status")[0] == 200
    finally:
        again.close()


def test_close_without_start(source):
    StatusServer(source.status, source.preview_png).close()


# -- the page in a browser -----------------------------------------------------------
class TextById(HTMLParser):
    """Text inside each element that has an id, nested text included."""

    VOID = {"img", "br", "meta", "input", "link", "hr"}

    def __init__(self):
        super().__init__()
        self.texts: dict[str, str] = {}
        self.imgs: list[dict] = []
        self.open: list[str | None] = []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "img":
            self.imgs.append(attrs)
        if tag in self.VOID:
            return
        self.open.append(attrs.get("id"))
        if attrs.get("id"):
            self.texts[attrs["id"]] = ""

    def handle_endtag(self, tag):
        if tag not in self.VOID and self.open:
            self.open.pop()

    def handle_data(self, data):
        for element_id in filter(None, self.open):
            self.texts[element_id] += data + " "


@pytest.mark.browser
def test_page_in_headless_chromium(server, tmp_path):
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.skip("chromium not installed (apt-get install chromium)")
    dom = subprocess.run(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu",
         f"--user-data-dir={tmp_path}", "--virtual-time-budget=5000",
         "--dump-dom", server.url],
        capture_output=True, text=True, timeout=60, check=True).stdout
    page = TextById()
    page.feed(dom)
    assert page.texts["iteration"].strip() == "7"
    # Thousands separators (issue 16); the raw counters keep every key.
    assert page.texts["photons"].strip() == "123,456"
    assert page.texts["committed"].strip() == "120,000"
    assert page.texts["photons_per_s"].strip() == "98,765"
    assert page.texts["jobs_in_flight"].strip() == "3"
    assert page.texts["eta"].strip() == "42 s"
    tracers = page.texts["tracers"].split()
    assert {"Tracer", "Chunks", "Queue", "tracer-a", "tracer-b"} <= set(tracers)
    raw = page.texts["tracers_raw"].split()
    assert {"id", "chunks", "queue", "load", "tracer-a", "tracer-b", "0.75"} <= set(raw)
    assert any(img.get("src", "").startswith("/preview.png") for img in page.imgs)
