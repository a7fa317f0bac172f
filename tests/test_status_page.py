"""The status page at a glance (issue 16).

- The server's history is bounded: never more than its capacity, every
  other sample dropped when full (the interval doubling), the whole render
  still covered, sampled at most once per interval, and its rates exact
  across the samples dropped.
- Tracer rates, states and warnings come from a real `ServerState`:
  registration, heartbeats, eviction, rejoin in place and after an
  eviction, refused results.
- The server process puts them in /status (over HTTP, on real sockets).
- In headless Chromium at 1280x900 the page has no horizontal scrollbar,
  shows the progress bar and three SVG charts with data, and its numbers
  change between two loads; a screenshot is taken (and, for a real render
  of cornell-caustic, copied to $DOSPPM_STATUS_SCREENSHOT: the README's).
"""
from __future__ import annotations

import itertools
import json
import os
import shutil
import struct
import subprocess
import threading
import time
import urllib.request

import numpy as np
import pytest

from dosppm_core.film import encode_png
from dosppm_core.settings import RenderSettings
from services import transport, wire
from services.server import http as status_http
from services.server.history import (
    REJOINED_SHOW_S,
    History,
    StatusHistory,
    TracerRates,
    progress,
)
from services.server.http import StatusServer
from services.server.node import ServerProcess
from services.server.options import Limits, ServerOptions
from services.server.state import ServerState
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.cli import free_port, start_dosppm
from tests.helpers.scenes import small_scene
from tests.test_http import TextById

pytestmark = pytest.mark.timeout(300)


# -- the history ---------------------------------------------------------------------
def test_history_stays_within_its_capacity_and_covers_the_whole_render():
    h = History(capacity=600, interval_s=1.0)
    for i in range(200_000):                        # 28 hours at a status every 0.5 s
        h.add(i * 0.5, photons=1000 * i, hit_points=10 * i, mean_radius=1.0 / (1 + i))
        assert len(h.samples) <= 600
    t = [s[0] for s in h.samples]
    assert t[0] == 0.0, "the start of the render is still there"
    assert t[-1] >= 199_999 * 0.5 - h.interval_s, "and its end"
    assert set(np.diff(t)) == {h.interval_s}, "evenly spaced"
    assert h.interval_s == 256.0 and len(h.samples) > 300


def test_history_drops_every_other_sample_when_full_and_doubles_its_interval():
    h = History(capacity=4, interval_s=1.0)
    for i in range(5):
        assert h.add(float(i), i, i)
    assert [s[0] for s in h.samples] == [0.0, 2.0, 4.0] and h.interval_s == 2.0
    assert not h.add(5.0, 5, 5), "closer than the new interval"
    assert h.add(6.0, 6, 6) and h.add(8.0, 8, 8)
    assert [s[0] for s in h.samples] == [0.0, 4.0, 8.0] and h.interval_s == 4.0


def test_history_samples_at_most_once_per_interval():
    h = History(interval_s=1.0)
    added = sum(h.add(i * 0.1, i, i) for i in range(101))     # 10 s of statuses every 0.1 s
    assert added == len(h.samples) == 11


def test_history_rates_are_exact_whatever_was_dropped():
    """Photons at 1000/s for 100 s, then 250/s: the rates over the window
    say so after downsampling, and the mean radius is carried along."""
    h = History(capacity=40, interval_s=1.0)
    photons = 0
    for i in range(1, 201):
        photons += 1000 if i <= 100 else 250
        h.add(float(i), photons, 2 * photons, mean_radius=0.5)
    s = h.series(window_s=5.0)
    assert h.interval_s == 8.0 and len(s["t"]) == len(h.samples) - 1
    rate = dict(zip(s["t"], s["photons_per_s"]))
    assert all(v == 1000.0 for t, v in rate.items() if t <= 100)
    assert all(v == 250.0 for t, v in rate.items() if t >= 112)
    assert s["hit_points_per_s"] == pytest.approx([2 * v for v in s["photons_per_s"]], abs=0.1)
    assert set(s["mean_radius"]) == {0.5}


def test_tracer_rates_over_the_last_heartbeats():
    r = TracerRates(window_s=5.0)
    for i in range(10):            # busy 0.5 s of each second, 1000 rays a second, 300 photon rays
        r.observe("a", float(i), {"busy_s": 0.5 * i, "rays_traced": 1000 * i, "photons_traced": 300 * i})
    busy, rays, photons = r.rates("a")
    assert busy == pytest.approx(0.5) and rays == pytest.approx(1000.0) and photons == pytest.approx(300.0)
    assert len(r.beats["a"]) <= 7
    r.observe("a", 10.0, {"busy_s": 0.0, "rays_traced": 0})     # a new process: counts from zero
    assert r.rates("a") == (None, None, None)
    r.keep_only(["b"])
    assert r.beats == {}


def test_progress_is_towards_the_limit_that_stops_the_render_first():
    p = progress(10.0, {"time": 25.0, "photons": None, "iterations": None},
                 {"time": 10.0, "photons": 0, "iterations": 0}, {"time": 1.0, "photons": 0, "iterations": 0})
    assert (p["stop"], p["fraction"], p["eta_s"], p["elapsed_s"]) == ("time", 0.4, 15.0, 10.0)
    # 1e6 photons at 1e5/s stop at 10 s, before a 60 s time limit.
    p = progress(5.0, {"time": 60.0, "photons": 1e6, "iterations": None},
                 {"time": 5.0, "photons": 5e5, "iterations": 3},
                 {"time": 1.0, "photons": 1e5, "iterations": 0.6})
    assert (p["stop"], p["fraction"], p["eta_s"], p["limit"]) == ("photons", 0.5, 5.0, 1e6)
    p = progress(0.0, {"time": None, "photons": None, "iterations": 8},
                 {"time": 0.0, "photons": 0, "iterations": 0}, {"time": 1.0, "photons": 0, "iterations": 0})
    assert (p["stop"], p["fraction"], p["eta_s"]) == ("iterations", 0.0, None)
    assert progress(3.0, {"time": None, "photons": None, "iterations": None}, {}, {})["stop"] is None


# -- tracer states and warnings from a real ServerState ----------------------------------
def _msg(msg_type, **fields):
    return wire.decode([bytes(f) for f in wire.encode(msg_type, **fields)])


def _register(state, tid, now):
    return state.on_register(tid, _msg("register", tracer_id=tid, capacity={"cores": 1, "memory_bytes": 0},
                                       endpoint=f"tcp://{tid}:1", has_store=True, store_key="k"), now)


def _heartbeat(state, tid, now, busy_s, rays, queue=0, resident=(), load_wait_s=0.0, idle_s=0.0):
    # Per chunk [chunk, in, out]: tracer a's chunk 0 and the chunk 2 it
    # served before b joined; b's chunk 2.
    portal = {"a": [[0, 10, 20], [2, 1, 2]], "b": [[2, 3, 4]]}.get(tid, [])
    state.on_message(tid, _msg("heartbeat", status={"busy_s": busy_s, "rays_traced": rays,
                                                    "load_wait_s": load_wait_s, "idle_s": idle_s,
                                                    "photons_traced": rays // 2, "queue": queue,
                                                    "resident": list(resident), "portal_by_chunk": portal,
                                                    "portal_rays_in": 10, "portal_rays_out": 20}), now)


@pytest.fixture()
def state():
    scene = small_scene("cornell-box", 32)
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 1)))
    return ServerState(provider.header, provider.tree, RenderSettings(photons_per_job=512, tile_pixels=256),
                       "k", options=ServerOptions(min_tracers=2))


def _update(history, state, now, phase="render", **counters):
    st = dict(state.status(), phase=phase)
    history.update(st, now, state, now if phase == "render" else None, None,
                   dict(state.counters, undeliverable=0, **counters))
    return st


def test_a_tracers_state_is_what_took_most_of_its_time(state):
    h = StatusHistory(origin_s=0.0)
    _register(state, "c", 0.0), _register(state, "d", 0.0)
    for i in range(6):       # c reads and sends messages; d waits for chunk loads
        _heartbeat(state, "c", float(i), 0.1 * i, 100 * i, load_wait_s=0.05 * i, idle_s=0.2 * i)
        _heartbeat(state, "d", float(i), 0.7 * i, 100 * i, load_wait_s=0.6 * i, idle_s=0.1 * i)
        st = _update(h, state, i + 0.1)
    rows = {t["id"]: t for t in st["tracers"]}
    assert rows["c"]["time"] == {"tracing": 0.05, "loading": 0.05, "idle": 0.2, "waiting": 0.7}
    assert rows["d"]["time"] == {"tracing": 0.1, "loading": 0.6, "idle": 0.1, "waiting": 0.2}
    assert (rows["c"]["state"], rows["d"]["state"]) == ("waiting", "loading")


def test_tracer_states_and_warnings(state):
    h = StatusHistory(origin_s=0.0)
    _register(state, "a", 0.0), _register(state, "b", 0.0)
    # A heartbeat a second, a status every half second (as in the server):
    # a is in its steps 80% of the time, a quarter of that waiting for chunk
    # loads, with rays queued; b idles with nothing queued. Each state is
    # what took most of its time, whatever the phase (issue 29: "idle" and
    # "busy 98%" side by side while draining).
    for i in range(6):
        _heartbeat(state, "a", float(i), 0.8 * i, 5000 * i, queue=4096, resident=[0, 2], load_wait_s=0.2 * i,
                   idle_s=0.1 * i)
        _heartbeat(state, "b", float(i), 0.05 * i, 100 * i, idle_s=0.9 * i)
        st = _update(h, state, i + 0.1, phase="draining")
        _update(h, state, i + 0.6, phase="draining")
    assert {t["id"]: t["state"] for t in st["tracers"]} == {"a": "tracing", "b": "idle"}
    st = _update(h, state, 5.2)
    rows = {t["id"]: t for t in st["tracers"]}
    assert rows["a"]["time"] == {"tracing": 0.6, "loading": 0.2, "idle": 0.1, "waiting": 0.1}
    assert rows["a"]["state"] == "tracing" and rows["a"]["busy"] == pytest.approx(0.8)
    assert rows["a"]["rays_per_s"] == pytest.approx(5000)
    assert rows["a"]["photons_per_s"] == pytest.approx(2500)
    assert rows["a"]["heartbeat_age_s"] == pytest.approx(0.2)
    assert rows["b"]["state"] == "idle" and rows["b"]["busy"] == pytest.approx(0.05)
    assert st["chunk_table"][0] == {"chunk": 0, "tracers": ["a"], "resident": ["a"],
                                    "portal_rays_in": 10, "portal_rays_out": 20}
    assert st["chunk_table"][2]["portal_rays_in"] == 4 and st["chunk_table"][2]["portal_rays_out"] == 6
    assert st["chunk_table"][1]["portal_rays_in"] == 0      # nobody reported chunk 1
    assert st["chunk_table"][1]["resident"] == [] and st["warnings"] == []

    assert _update(h, state, 9.0)["tracers"][1]["state"] == "silent", "no heartbeat from b for 4 s"
    state.evict("b", "silent for 10.0 s")
    st = _update(h, state, 10.0)
    assert [t["id"] for t in st["tracers"]] == ["a"], "an evicted tracer is not listed as registered"
    assert st["evictions"] == [{"id": "b", "reason": "silent for 10.0 s", "t_s": 10.0}]
    assert st["warnings"][0]["text"] == "tracer b evicted: silent for 10.0 s"

    _register(state, "b", 11.0)                      # back after its eviction
    _register(state, "a", 11.0)                      # cut off, registers again in place
    state.counters["refused"] += 2
    st = _update(h, state, 11.5)
    assert {t["id"]: t["state"] for t in st["tracers"]} == {"a": "rejoined", "b": "rejoined"}
    texts = [w["text"] for w in st["warnings"]]
    assert "tracer a registered again: jobs in flight re-emitted" in texts
    assert "tracer b rejoined after its eviction" in texts
    assert any(t.startswith("refused 2:") for t in texts)
    assert st["warnings"][0]["t_s"] == 11.5 and len(texts) == 4, "newest first, each event once"
    assert len(_update(h, state, 12.0)["warnings"]) == 4
    _heartbeat(state, "a", 11.5 + REJOINED_SHOW_S, 100.0, 10**6, queue=1)
    later = _update(h, state, 12.0 + REJOINED_SHOW_S)
    assert {t["id"]: t["state"] for t in later["tracers"]}["a"] == "tracing"


# -- the server process ------------------------------------------------------------------
def _get_status(url: str) -> dict:
    with urllib.request.urlopen(url + "status", timeout=5) as r:
        return json.load(r)


def _status_until(url: str, ok, timeout_s: float = 30.0) -> dict:
    deadline, last = time.monotonic() + timeout_s, None
    while time.monotonic() < deadline:
        last = _get_status(url)
        if ok(last):
            return last
        time.sleep(0.2)
    raise AssertionError(f"status never matched; last: {json.dumps(last)[:3000]}")


def test_the_server_process_serves_what_the_page_needs():
    """A real server on sockets, waiting for 5 tracers; a probe registers
    and sends heartbeats, then registers again."""
    scene = small_scene("cornell-box", 16)
    store = MemoryChunks(scene, uniform_tree(root_box(scene), (1, 1, 1)))
    store.key, store.manifest, store.path, store.chunk_count = "k", None, "", 1
    server = ServerProcess(store, RenderSettings(threads=1), ServerOptions(
        bind="tcp://127.0.0.1:*", http=("127.0.0.1", 0), out="", limits=Limits(seconds=600), min_tracers=5))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    d = transport.dealer(b"probe")
    try:
        d.connect(server.endpoint)
        register = wire.encode("register", tracer_id="probe", capacity={"cores": 1, "memory_bytes": 0},
                               endpoint="tcp://127.0.0.1:1", has_store=True, store_key="k")
        d.send(register)
        for i in range(4):
            d.send(wire.encode("heartbeat", status={"queue": 0, "busy_s": 0.25 * i, "rays_traced": 100 * i,
                                                    "resident": [0]}))
            time.sleep(0.5)
        st = _status_until(server.status_url, lambda s: s["tracers"] and s["tracers"][0]["busy"] is not None)
        assert st["phase"] == "waiting" and st["waiting_for"]["registered"] == 1
        assert st["progress"]["stop"] == "time" and st["progress"]["limit"] == 600
        assert st["eta_s"] == st["progress"]["eta_s"] == 600
        assert st["history"] == {"t": [], "photons_per_s": [], "hit_points_per_s": [], "mean_radius": []}
        t = st["tracers"][0]
        assert t["state"] in ("tracing", "waiting") and t["busy"] == pytest.approx(0.5, abs=0.15)
        assert sum(t["time"].values()) == pytest.approx(1.0, abs=0.01)
        assert 0 <= t["heartbeat_age_s"] < 3 and t["rays_per_s"] > 0
        assert st["chunk_table"] == [{"chunk": 0, "tracers": ["probe"], "resident": ["probe"],
                                      "portal_rays_in": 0, "portal_rays_out": 0}]
        d.send(register)
        st = _status_until(server.status_url, lambda s: s["warnings"])
        assert st["warnings"][0]["text"] == "tracer probe registered again: jobs in flight re-emitted"
        assert st["tracers"][0]["state"] == "rejoined"
        assert {"photons_committed", "photons_per_s", "hit_points_per_s", "jobs_in_flight", "eta_s",
                "counters", "path_ends"} <= set(st), "the keys tools read are still there"
    finally:
        d.close(linger_ms=0)
        server._signals = 2
        thread.join(30)
    assert not thread.is_alive()


# -- the page in Chromium ----------------------------------------------------------------------
# Appended to the page under test only: after the page has polled /status
# a few times, record the layout's width with every <details> closed and
# then open, where --dump-dom can read it.
PROBE = """<script>
setTimeout(() => {
  const root = document.documentElement, out = document.body.dataset;
  out.innerWidth = window.innerWidth;
  out.clientWidth = root.clientWidth;
  out.scrollWidthClosed = root.scrollWidth;
  for (const d of document.querySelectorAll("details")) d.open = true;
  out.scrollWidthOpen = root.scrollWidth;
}, 4500);
</script>
"""


def _chromium():
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("chromium not installed (apt-get install chromium)")
    return chromium


def _browse(url: str, profile, *extra: str) -> str:
    """Chromium headless at 1280x900, 5 s of page time; its stdout."""
    return subprocess.run(
        [_chromium(), "--headless", "--no-sandbox", "--disable-gpu", f"--user-data-dir={profile}",
         "--window-size=1280,900", "--virtual-time-budget=5000", *extra, url],
        capture_output=True, text=True, timeout=90, check=True).stdout


def _png_size(path) -> tuple[int, int]:
    with open(path, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


class Page(TextById):
    """Also the body's data attributes, the bar's style and every polyline
    per chart."""

    def __init__(self):
        super().__init__()
        self.body: dict = {}
        self.attrs_by_id: dict[str, dict] = {}
        self.polylines: dict[str, list[str]] = {}

    def handle_starttag(self, tag, attrs):
        super().handle_starttag(tag, attrs)
        a = dict(attrs)
        if tag == "body":
            self.body = a
        if a.get("id"):
            self.attrs_by_id[a["id"]] = a
        if tag == "polyline":
            chart = next((i for i in reversed(self.open) if i and i.startswith("chart_")), None)
            self.polylines.setdefault(chart, []).append(a.get("points", ""))


def _load(url, profile) -> Page:
    page = Page()
    page.feed(_browse(url, profile, "--dump-dom"))
    return page


def _fake_farm():
    """A status source for a farm of 12 tracers and 24 chunks whose numbers
    move on every call, as a real render's do."""
    calls = itertools.count()

    def status():
        n = next(calls)
        t = list(range(1, 30 + n))
        ids = [f"render-node-{i:02d}.farm.example.org" for i in range(12)]
        return {
            "iteration": 7 + n, "photons_emitted": 3_811_093 + 250_000 * n, "photons_committed": 3_700_000,
            "photons_per_s": 152_443.7 + n, "hit_points_per_s": 16_384.0, "jobs_in_flight": 212,
            "eta_s": 15.0 - n,
            "phase": "render", "waiting_for": None, "seconds": 10.0 + n, "server_s": 14.0 + n, "chunks": 24,
            "progress": {"elapsed_s": 10.0 + n, "stop": "time", "limit": 25.0, "value": 10.0 + n,
                         "fraction": (10.0 + n) / 25, "eta_s": 15.0 - n},
            "history": {"t": t, "photons_per_s": [150_000 - (50_000 if 8 < x < 12 else 0) for x in t],
                        "hit_points_per_s": [16_000 + 1000 * (x % 3) for x in t],
                        "mean_radius": [0.02 * x ** -0.15 for x in t]},
            "warnings": [{"t_s": 9.5, "kind": "evicted",
                          "text": "tracer render-node-99 evicted: silent for 10.2 s"}],
            "evictions": [{"id": "render-node-99", "reason": "silent for 10.2 s", "t_s": 9.5}],
            "chunk_table": [{"chunk": k, "tracers": [ids[k % 12]], "resident": [ids[k % 12]] if k % 3 else [],
                             "portal_rays_in": 123_456, "portal_rays_out": 654_321} for k in range(24)],
            "path_ends": {"absorbed": 1_234_567, "escaped": 2345},
            "tracers": [{"id": tid, "endpoint": f"tcp://{tid}:5600",
                         "chunks": list(range(i, 24, 12)) + [40, 41, 42],
                         "queue": 65_536 * (i % 2), "rays_sent": 3_811_093, "results": 812, "resident": [i],
                         "busy_s": 9.1, "steps": 400, "rays_traced": 5_123_456 + 1000 * n,
                         "portal_rays_out": 654_321, "portal_rays_in": 123_456, "forwarded_rays": 0,
                         "cpu_s": 18.25, "bytes_to_server": 123_456_789, "bytes_to_peers": 23_456_789,
                         "heartbeat_age_s": 0.4, "busy": 0.93 if i % 2 else 0.1, "rays_per_s": 512_345.6 + n,
                         "photons_per_s": 256_172.8 + n,
                         "time": {"tracing": 0.81, "loading": 0.12, "waiting": 0.04, "idle": 0.03} if i % 2
                         else {"tracing": 0.07, "loading": 0.03, "waiting": 0.05, "idle": 0.85},
                         "state": "tracing" if i % 2 else "idle"} for i, tid in enumerate(ids)],
        }
    return status


@pytest.mark.browser
def test_page_in_chromium_at_1280x900(tmp_path, monkeypatch):
    _chromium()
    monkeypatch.setattr(status_http, "PAGE", status_http.PAGE.replace("</body>", PROBE + "</body>"))
    png = encode_png(np.full((64, 64, 3), 90, np.uint8))
    with StatusServer(_fake_farm(), lambda: png) as srv:
        first, second = _load(srv.url, tmp_path / "a"), _load(srv.url, tmp_path / "b")
        shot = tmp_path / "status-page.png"
        _browse(srv.url, tmp_path / "c", f"--screenshot={shot}")
    assert _png_size(shot) == (1280, 900)
    for page in (first, second):
        assert "status unavailable" not in page.texts["state"]
        width = int(page.body["data-inner-width"])
        assert width == 1280
        # No horizontal scrollbar, with every <details> closed or open
        # (the client width leaves out a vertical scrollbar, if drawn).
        client = int(page.body["data-client-width"])
        assert 1200 < client <= width
        assert int(page.body["data-scroll-width-closed"]) <= client
        assert int(page.body["data-scroll-width-open"]) <= client
        fill = page.attrs_by_id["bar_fill"]["style"]
        assert "width:" in fill.replace(" ", "") and not fill.replace(" ", "").startswith("width:0%")
        assert page.texts["bar_text"].strip().endswith("%")
        assert "ETA" in page.texts["progress_line"] and "time limit" in page.texts["progress_line"]
        assert set(page.polylines) == {"chart_photons", "chart_hit_points", "chart_radius"}
        for points in page.polylines.values():
            assert len(points) == 1 and len(points[0].split()) >= 29
        assert page.texts["phase"].strip() == "Rendering"
        assert "render-node-99 evicted" in page.texts["warnings"]
        tracers = page.texts["tracers"]
        assert "65,536" in tracers and "idle" in tracers and "evicted" in tracers
        assert "81 / 12 / 4 %" in tracers and "Tracing / loading / waiting" in tracers
        assert "3,811,093" in page.texts["tracers_raw"], "raw counters, with separators"
        assert "654,321" in page.texts["chunks"]
    # The page polls: numbers move between two loads (and within each).
    assert first.texts["photons"] != second.texts["photons"]
    assert first.texts["iteration"] != second.texts["iteration"]
    assert first.polylines["chart_photons"] != second.polylines["chart_photons"]


@pytest.mark.browser
def test_the_probe_sees_a_page_too_wide(tmp_path, monkeypatch):
    """The negative control of the scrollbar check: one element 2000 px wide."""
    _chromium()
    wide = '<div style="width: 2000px">wide</div>'
    monkeypatch.setattr(status_http, "PAGE", status_http.PAGE.replace("</body>", wide + PROBE + "</body>"))
    with StatusServer(_fake_farm(), lambda: None) as srv:
        page = _load(srv.url, tmp_path / "a")
    assert int(page.body["data-scroll-width-closed"]) > int(page.body["data-client-width"])


@pytest.mark.slow
@pytest.mark.browser
def test_page_of_a_real_render(tmp_path):
    """`dosppm render cornell-caustic` with 4 chunks on 2 tracers for 25 s,
    the page opened mid-render: charts with real samples, a chunk table,
    no horizontal overflow in the screenshot's window. The screenshot is
    copied to $DOSPPM_STATUS_SCREENSHOT if set (docs/status-page.png)."""
    _chromium()
    port = free_port()
    url = f"http://127.0.0.1:{port}/"
    proc = start_dosppm("render", "cornell-caustic", "--width", "256", "--height", "256", "--chunks", "4",
                        "--tracers", "2", "--time", "25", "--out", tmp_path / "img.exr", "--http",
                        f"127.0.0.1:{port}", "--store-cache", tmp_path / "stores", "--quiet",
                        stderr=subprocess.PIPE, text=True)
    try:
        st = _wait_for_render(url, proc, lambda s: len(s.get("history", {}).get("t", [])) >= 10)
        shot = tmp_path / "status-page.png"
        _browse(url, tmp_path / "a", f"--screenshot={shot}")
        page = _load(url, tmp_path / "b")
        assert proc.wait(120) == 0, proc.stderr.read()[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert _png_size(shot) == (1280, 900)
    assert set(page.polylines) == {"chart_photons", "chart_hit_points", "chart_radius"}
    assert len(st["chunk_table"]) == 4 and max(st["history"]["photons_per_s"]) > 0
    assert "Rendering" in page.texts["phase"] and page.texts["chunks"].split()[:2] == ["Chunk", "Tracers"]
    if os.environ.get("DOSPPM_STATUS_SCREENSHOT"):
        shutil.copyfile(shot, os.environ["DOSPPM_STATUS_SCREENSHOT"])


def _wait_for_render(url: str, proc, ok, timeout_s: float = 240.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            st = _get_status(url)
            if st.get("phase") == "render" and ok(st):
                return st
        except OSError:
            pass
        time.sleep(0.5)
    raise AssertionError(f"the render never got there (exit {proc.poll()})")
