"""The server process on its socket, driven by a bare transport peer: a tracer
speaking another protocol version is refused with a reason, garbage gets an
error reply and the server keeps serving, and heartbeats flow both ways."""
from __future__ import annotations

import os
import re
import threading
import time

import msgpack
import numpy as np
import pytest

from dosppm_core.settings import RenderSettings
from services import transport, wire
from services.server.node import ServerProcess
from services.server.options import Limits, ServerOptions
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.paths import REPO
from tests.helpers.scenes import small_scene


@pytest.fixture()
def server():
    scene = small_scene("cornell-box", 16)
    store = MemoryChunks(scene, uniform_tree(root_box(scene), (1, 1, 1)))
    store.key, store.manifest, store.path, store.chunk_count = "k", None, "", 1
    s = ServerProcess(store, RenderSettings(threads=1), ServerOptions(
        bind="tcp://127.0.0.1:*", http=None, out="", limits=Limits(seconds=600), min_tracers=5))
    t = threading.Thread(target=s.run, daemon=True)
    t.start()
    yield s
    s._signals = 2                   # what a second SIGINT does: stop now
    t.join(30)
    assert not t.is_alive()


def _dealer(server, ident=b"probe"):
    d = transport.dealer(ident)
    d.connect(server.endpoint)
    return d


def _reply(d, timeout_ms=5000, want=None):
    deadline = time.monotonic() + timeout_ms / 1000
    while time.monotonic() < deadline:
        if d.poll(200):
            _, msg = d.recv()
            if want is None or msg.type in want:
                return msg
    raise AssertionError("no reply")


def test_a_tracer_of_another_protocol_version_is_refused_with_a_reason(server):
    d = _dealer(server)
    frames = wire.encode("register", tracer_id="old", capacity={"cores": 1, "memory_bytes": 0},
                         endpoint="tcp://127.0.0.1:1", has_store=False)
    header = msgpack.unpackb(bytes(frames[0]))
    header["v"] = wire.PROTOCOL_VERSION + 1
    d.send([msgpack.packb(header), *frames[1:]])
    msg = _reply(d)
    assert msg.type == "refused"
    assert f"tracer speaks {wire.PROTOCOL_VERSION + 1}, server speaks {wire.PROTOCOL_VERSION}" in msg.reason
    assert "same dosppm release" in msg.reason
    assert server.state.tracers == {}
    d.close(linger_ms=0)


def test_garbage_gets_an_error_and_the_server_keeps_serving(server):
    d = _dealer(server)
    d.send([b"\xc1not msgpack"])
    assert _reply(d).type == "error"
    d.send(wire.encode("results", chunk=0, ends=np.zeros(5, np.int64),
                                 job_ids=np.zeros(0, np.int64), job_fed=np.zeros(0, np.int64),
                                 job_left=np.zeros(0, np.int64), credit_job=np.zeros(0, np.int64),
                          credit_exp=np.zeros(0, np.int64)))
    msg = _reply(d)
    assert msg.type == "error" and "not registered" in msg.reason
    # Still serving: a proper registration is welcomed, then heartbeats come.
    d.send(wire.encode("register", tracer_id="probe", capacity={"cores": 1, "memory_bytes": 0},
                                 endpoint="tcp://127.0.0.1:1", has_store=True, store_key="k"))
    assert _reply(d, want={"welcome"}).chunks == [0]
    assert _reply(d, 3000, want={"heartbeat"}).type == "heartbeat"
    d.send(wire.encode("heartbeat", status={"queue": 0}))
    time.sleep(0.5)
    assert server.state.tracers["probe"].status == {"queue": 0}
    d.close(linger_ms=0)


def test_a_snapshot_waiting_for_the_statistics_does_not_stall_the_message_loop(tmp_path):
    """An update holds the statistics' lock for seconds when a flood of
    deposits is applied. The image snapshot reads them under that lock:
    it must wait on the statistics thread, not in the loop whose
    heartbeats tell tracers the server is there (past SERVER_SILENT_S,
    5 s, they register again and every job in flight is re-emitted)."""
    scene = small_scene("cornell-box", 16)
    store = MemoryChunks(scene, uniform_tree(root_box(scene), (1, 1, 1)))
    store.key, store.manifest, store.path, store.chunk_count = "k", None, "", 1
    s = ServerProcess(store, RenderSettings(threads=1), ServerOptions(
        bind="tcp://127.0.0.1:*", http=None, out=str(tmp_path / "img.exr"), limits=Limits(seconds=600),
        min_tracers=5, snapshot_interval_s=0.2))
    s.state.eye_completed = 1                        # a snapshot is due at every interval
    t = threading.Thread(target=s.run, daemon=True)
    t.start()
    d = _dealer(s)
    try:
        d.send(wire.encode("register", tracer_id="probe", capacity={"cores": 1, "memory_bytes": 0},
                           endpoint="tcp://127.0.0.1:1", has_store=True, store_key="k"))
        _reply(d, want={"welcome"})
        with s.statistics.lock:                      # a long update
            beats, t0 = [], time.monotonic()
            while time.monotonic() - t0 < 3.5:
                beats.append(_reply(d, 3000, want={"heartbeat"}) and time.monotonic())
        assert max(np.diff([t0, *beats])) < 2.0, np.diff([t0, *beats])
        deadline = time.monotonic() + 10             # the lock free, the snapshot is written
        while not (tmp_path / "img.exr").exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert (tmp_path / "img.exr").exists()
    finally:
        d.close(linger_ms=0)
        s._signals = 2
        t.join(30)
    assert not t.is_alive()


def test_chunks_are_requested_by_id_only(server):
    """A chunk request names an index; anything out of range is an error,
    and there is no field through which a path could be asked for."""
    assert set(wire.MESSAGES["chunk_request"].fields) == {"chunk"}
    d = _dealer(server, b"reader")
    d.send(wire.encode("register", tracer_id="reader", capacity={"cores": 1, "memory_bytes": 0},
                                 endpoint="tcp://127.0.0.1:1", has_store=True, store_key="k"))
    _reply(d, want={"welcome"})
    d.send(wire.encode("chunk_request", chunk=7))
    msg = _reply(d, want={"error"})
    assert "no chunk 7" in msg.reason and msg.about == "chunk_request"
    d.close(linger_ms=0)


def test_nothing_executes_data():
    """No pickle, eval, exec or shell anywhere in the product or its harness."""
    root = REPO
    bad = re.compile(r"\bimport pickle\b|\bpickle\.\w+\(|\beval\(|\bexec\(|shell=True|os\.system\(|os\.popen\(")
    hits = []
    for package in ("dosppm_core", "services", "harness"):
        for folder, _, files in os.walk(os.path.join(root, package)):
            for name in files:
                if name.endswith(".py"):
                    with open(os.path.join(folder, name), encoding="utf-8") as f:
                        hits += [f"{name}:{i + 1}" for i, line in enumerate(f) if bad.search(line)]
    assert not hits, hits
