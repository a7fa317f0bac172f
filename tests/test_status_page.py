"""The status page at a glance (issue 16): what the server adds to /status.

- The server's history is bounded: never more than its capacity, every
  other sample dropped when full (the interval doubling), the whole render
  still covered, sampled at most once per interval, and its rates exact
  across the samples dropped.
- Tracer rates, states and warnings come from a real `ServerState`:
  registration, heartbeats, eviction, rejoin in place and after an
  eviction, refused results.
- The server process puts them in /status (over HTTP, on real sockets).
"""
from __future__ import annotations

import json
import threading
import time
import urllib.request

import numpy as np
import pytest

from dosppm_core.settings import RenderSettings
from services import transport, wire
from services.server.history import (
    REJOINED_SHOW_S,
    History,
    StatusHistory,
    TracerRates,
    progress,
)
from services.server.node import Limits, ServerProcess
from services.server.state import ServerState
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.scenes import small_scene

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
    for i in range(10):            # busy 0.5 s of each second, 1000 rays a second
        r.observe("a", float(i), {"busy_s": 0.5 * i, "rays_traced": 1000 * i})
    busy, rays = r.rates("a")
    assert busy == pytest.approx(0.5) and rays == pytest.approx(1000.0)
    assert len(r.beats["a"]) <= 7
    r.observe("a", 10.0, {"busy_s": 0.0, "rays_traced": 0})     # a new process: counts from zero
    assert r.rates("a") == (None, None)
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


def _heartbeat(state, tid, now, busy_s, rays, queue=0, resident=()):
    state.on_message(tid, _msg("heartbeat", status={"busy_s": busy_s, "rays_traced": rays, "queue": queue,
                                                    "resident": list(resident), "portal_rays_in": 10,
                                                    "portal_rays_out": 20}), now)


@pytest.fixture()
def state():
    scene = small_scene("cornell-box", 32)
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 2, 1)))
    return ServerState(provider.header, provider.tree, RenderSettings(photons_per_job=512, tile_pixels=256),
                       "k", min_tracers=2)


def _update(history, state, now, phase="render", **counters):
    st = dict(state.status(), phase=phase)
    history.update(st, now, state, now if phase == "render" else None, None,
                   dict(state.counters, undeliverable=0, **counters))
    return st


def test_tracer_states_and_warnings(state):
    h = StatusHistory(origin_s=0.0)
    _register(state, "a", 0.0), _register(state, "b", 0.0)
    # A heartbeat a second, a status every half second (as in the server):
    # a works 80% of the time with rays queued, b idles with nothing queued.
    for i in range(6):
        _heartbeat(state, "a", float(i), 0.8 * i, 5000 * i, queue=4096, resident=[0, 2])
        _heartbeat(state, "b", float(i), 0.05 * i, 100 * i)
        st = _update(h, state, i + 0.1, phase="waiting")
        _update(h, state, i + 0.6, phase="waiting")
    assert {t["id"]: t["state"] for t in st["tracers"]} == {"a": "idle", "b": "idle"}
    st = _update(h, state, 5.2)
    rows = {t["id"]: t for t in st["tracers"]}
    assert rows["a"]["state"] == "active" and rows["a"]["busy"] == pytest.approx(0.8)
    assert rows["a"]["rays_per_s"] == pytest.approx(5000)
    assert rows["a"]["heartbeat_age_s"] == pytest.approx(0.2)
    assert rows["b"]["state"] == "starved" and rows["b"]["busy"] == pytest.approx(0.05)
    assert st["chunk_table"][0] == {"chunk": 0, "tracers": ["a"], "resident": ["a"],
                                    "portal_rays_in": 10, "portal_rays_out": 20}
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
    assert {t["id"]: t["state"] for t in later["tracers"]}["a"] == "active"


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
    server = ServerProcess(store, RenderSettings(threads=1), bind="tcp://127.0.0.1:*", http=("127.0.0.1", 0),
                           out="", limits=Limits(seconds=600), min_tracers=5)
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
        assert t["state"] == "idle" and t["busy"] == pytest.approx(0.5, abs=0.15)
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
